"""Prognosis: the remaining useful life of each unit from its calibrated health.

``prognose(model, train, test, ...)`` calibrates run-to-failure units and units in
service, learns from the former how the health parameters degrade and where units fail
(:mod:`~jaxcal.prognosis.degradation`), and predicts each unit's first crossing of a
failure boundary with an interval (:mod:`~jaxcal.prognosis.predict`). The command line
is ``python -m jaxcal.prognose`` (docs/prognosis.md).
"""

from jaxcal.prognosis.degradation import DegradationConfig, DegradationModel, fit
from jaxcal.prognosis.pipeline import (
    Prognosis,
    PrognosisConfig,
    prognose,
    prognose_trajectories,
)
from jaxcal.prognosis.predict import RulPrediction, predict
from jaxcal.prognosis.score import phm08_score, read_truth, score
from jaxcal.prognosis.trajectories import Trajectories, from_arrays, from_result

__all__ = [
    "DegradationConfig", "DegradationModel", "Prognosis", "PrognosisConfig",
    "RulPrediction", "Trajectories", "fit", "from_arrays", "from_result", "phm08_score",
    "predict", "prognose", "prognose_trajectories", "read_truth", "score",
]  # fmt: skip
