"""Closing the loop: find the residual, trace it to an effect the model lacks, add it.

``diagnose_record(record, engine, declared, cfg)`` calibrates the declared health
modifiers, ranks a library of candidate effects against the residual (BIC and
likelihood-ratio evidence, confounding flags), falls back to a discrepancy delta(w)
when nothing in the library explains it, adds the winner and reports the error before
and after. ``jaxcal.diagnosis.report.write_report`` writes the result (matplotlib: imported
only there); ``python -m jaxcal.diagnose`` is the command line.
"""

from jaxcal.diagnosis.effects import Candidate, build_library, linearize
from jaxcal.diagnosis.pipeline import DiagnosisResult, LoopConfig, diagnose_record
from jaxcal.diagnosis.synthetic import KINDS, SyntheticConfig, make_synthetic_record

__all__ = [
    "KINDS",
    "Candidate",
    "DiagnosisResult",
    "LoopConfig",
    "SyntheticConfig",
    "build_library",
    "diagnose_record",
    "linearize",
    "make_synthetic_record",
]
