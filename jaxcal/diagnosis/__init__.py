"""The diagnosis: find the residual, trace it to an effect the model lacks, add it.

``diagnose(data, model, declared, cfg)`` calibrates the declared parameters of any
:class:`jaxcal.Model` (static, or with hidden states: output-error form, the states
simulated with every candidate in the model) on a
:class:`~jaxcal.data.dataset.Dataset`, ranks the effect kinds of
:mod:`jaxcal.diagnosis.kinds.table` built
from the model (its undeclared parameters, drifting or stepping; its registered
effects; condition offsets; output bias, gain, drift and step), each fleet-wide or in
the units that carry it, against the prewhitened residual (an AR(p) noise model per
output, :mod:`jaxcal.diagnosis.residuals.noise`), falls back to a discrepancy delta(w)
when nothing in the
library explains it, adds the winner and reports the error before and after, and the
extended model (:mod:`jaxcal.diagnosis.report.extended`).
``jaxcal.diagnosis.report.write.write_report`` writes
the result; ``python -m jaxcal.diagnose`` is the command line. Submodules are imported
on first use.
"""

import importlib

_EXPORTS = {
    "KINDS": "jaxcal.diagnosis.kinds.table",
    "Candidate": "jaxcal.diagnosis.kinds.table",
    "EffectKind": "jaxcal.diagnosis.kinds.table",
    "build_library": "jaxcal.diagnosis.kinds.table",
    "DiagnosisResult": "jaxcal.diagnosis.pipeline",
    "LoopConfig": "jaxcal.diagnosis.pipeline",
    "diagnose": "jaxcal.diagnosis.pipeline",
    "SyntheticConfig": "jaxcal.diagnosis.data.synthetic",
    "make_synthetic_data": "jaxcal.diagnosis.data.synthetic",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'jaxcal.diagnosis' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
