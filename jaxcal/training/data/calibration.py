"""The calibration data set of a training run: padded ``[U, T, ...]`` arrays per split
and the one :class:`~jaxcal.problem.Problem` they define.

:class:`CalibrationData` is what training, evaluation and the paper's comparison read:
the train / validation / test units as :class:`~jaxcal.data.padded.Padded` (the one
padded container) and the problem (model, declared parameters, used outputs, action
box, normalisation over the training units in the run's dtype, training input
range), which :func:`training_problem` derives from the training units: the run's
one normalisation, made there once and carried, never recomputed. Its sources, an
N-CMAPSS file (:mod:`jaxcal.models.turbofan.training`, the turbofan's) and
any model's rows (:mod:`jaxcal.training.data.tables`), fill it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxcal.data.normalisation import column_stats
from jaxcal.data.padded import Padded
from jaxcal.model import Model
from jaxcal.problem import InputRange, Normalisation, Problem, provisional_noise


class CalibrationData(NamedTuple):
    """Everything a run needs from its data.

    Attributes:
        train, val, test: the splits; ``val`` is ``None`` when no unit is held out.
        problem: the :class:`~jaxcal.problem.Problem`: model, declared parameters
            (``theta_names``, action box ``theta_low``/``theta_high``, the other
            parameters' values ``theta_base``), used outputs, normalisation and
            input range of the training units.
        info: provenance (path, sample rate, rows and units per split).
    """

    train: Padded
    val: Padded | None
    test: Padded
    problem: Problem
    info: dict


def training_problem(
    model: Model,
    train: Padded,
    theta_names, output_names, theta_base, theta_low, theta_high,
    norm_dtype=np.float64,
) -> Problem:  # fmt: skip
    """The problem of a run on its ``train`` units.

    Its normalisation is the run's one (:func:`training_norm`): computed here, in the
    run's dtype ``norm_dtype``, and carried from here to the environment, the
    deployed policy and the run's ``data.json``. The input range is float64 over the
    training units' valid rows; the noise provisional, 1 % of each output's float64
    spread (:func:`output_spread`; the policy's filter step reads it)."""
    rows = np.asarray(train.mask, bool)
    w = np.asarray(train.w, np.float64)[rows]
    x = np.asarray(train.x, np.float64)[rows]
    noise_std, noise_source = provisional_noise(output_spread(train))
    return Problem(
        model=model,
        theta_names=tuple(theta_names),
        output_names=tuple(output_names),
        theta_base=np.asarray(theta_base, np.float64),
        theta_low=np.asarray(theta_low, np.float64),
        theta_high=np.asarray(theta_high, np.float64),
        norm=training_norm(train, norm_dtype),
        noise_std=noise_std,
        input_range=InputRange(w.min(0), w.max(0), x.min(0), x.max(0)),
        noise_source=noise_source,
    )


def training_norm(train: Padded, dtype) -> Normalisation:
    """The run's normalisation: mean and std over the valid rows of the ``train``
    units cast to ``dtype`` (the run's: float32 unless a float64 model runs its own
    step), computed in that dtype and stored as float64 copies (exact). A float32
    run so normalises with the exact float32 statistics it always had, which differ
    from the float64 ones cast to float32 by up to ~1e-4 relative (C-MAPSS)."""
    rows = np.asarray(train.mask, bool)
    w, x = (np.asarray(a).astype(dtype)[rows] for a in (train.w, train.x))
    norm = Normalisation.of(w, x, dtype=None)
    return Normalisation(*(np.asarray(a, np.float64) for a in norm))


def output_spread(train: Padded) -> np.ndarray:
    """``[S]`` each output's float64 std over the valid rows of the ``train`` units (a
    constant output 1): the scale of the provisional noise and of the cost floor of
    simulated units
    (:meth:`jaxcal.training.data.simulated.Simulations.with_noise_floor`),
    which have always read the float64 spread, not the run's normalisation."""
    x = np.asarray(train.x, np.float64)[np.asarray(train.mask, bool)]
    return column_stats(x)[1]
