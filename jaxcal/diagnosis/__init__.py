"""The diagnosis: find the residual, trace it to an effect the model lacks, add it.

``diagnose(data, model, declared, cfg)`` calibrates the declared parameters of any
static :class:`jaxcal.Model` on a :class:`~jaxcal.data.dataset.Dataset`, ranks a
library of candidate effects built from the model (its undeclared parameters, its
registered effects, generic condition offsets and output bias / gain / drift) against
the residual (BIC and likelihood-ratio evidence, confounding flags), falls back to a
discrepancy delta(w) when nothing in the library explains it, adds the winner and
reports the error before and after. ``jaxcal.diagnosis.report.write_report`` writes
the result (matplotlib: imported only there); ``python -m jaxcal.diagnose`` is the
command line.
"""

from jaxcal.diagnosis.effects import FAMILIES, Candidate, build_library, linearize
from jaxcal.diagnosis.pipeline import (
    DiagnosisResult,
    LoopConfig,
    diagnose,
    diagnose_record,
)
from jaxcal.diagnosis.synthetic import (
    SyntheticConfig,
    kinds,
    make_synthetic_data,
)

__all__ = [
    "FAMILIES",
    "Candidate",
    "DiagnosisResult",
    "LoopConfig",
    "SyntheticConfig",
    "build_library",
    "diagnose",
    "diagnose_record",
    "kinds",
    "linearize",
    "make_synthetic_data",
]
