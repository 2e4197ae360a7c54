"""jaxcal: real-time calibration of physics-based models in JAX.

The public front::

    import jaxcal

    model = jaxcal.Model.from_function(fn, conditions=..., parameters=..., outputs=...)
    result = jaxcal.calibrate(model, "data.csv", method="ukf")  # or "ls", "e2e"
    turbofan = jaxcal.models.load("cmapss")
    data = jaxcal.read_dataset("data.parquet", model)           # a jaxcal.Dataset

Layers (imports flow one way, downwards; ``tests/test_architecture.py`` holds the
order): the host-only leaves (``runs/``, ``settings``, ``precision``, ``cache``,
``numerics/``, ``plotting``) -> ``model`` -> ``physics/`` -> ``data/`` -> ``problem``
-> ``models/`` -> ``nets/`` / ``surrogate/`` / ``envs/`` / ``agents/`` ->
``calibrators/`` (the methods, the front door, reading a trained run) -> ``training/``
(the job) -> ``deploy/`` (streaming) -> ``diagnosis/`` / ``fleet/`` / ``paper/`` ->
``cli/`` (every ``python -m jaxcal.<tool>``; the old module paths are shims that
forward there). A model carries its own file formats (``Model.file_readers``); the
registry names the built-in models' training files (``jaxcal.models.TRAINING_FILES``).
Importing the package loads nothing heavy: the names below are imported on first use,
and float64 is switched on only by entry points (:func:`jaxcal.precision.enable_x64`).
"""

import importlib

from jaxcal.version import __version__  # noqa: F401 (jaxcal.__version__)

_EXPORTS = {
    "Model": ("jaxcal.model", "Model"),
    "Parameter": ("jaxcal.model", "Parameter"),
    "Variable": ("jaxcal.model", "Variable"),
    "Problem": ("jaxcal.problem", "Problem"),
    "Dataset": ("jaxcal.data.dataset", "Dataset"),
    "read_dataset": ("jaxcal.data.readers", "read_dataset"),
    "calibrate": ("jaxcal.calibrators.front.door", "calibrate"),
    "CalibrationResult": ("jaxcal.calibrators.front.result", "CalibrationResult"),
    "models": ("jaxcal.models", None),
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'jaxcal' has no attribute {name!r}")
    module, attr = _EXPORTS[name]
    value = importlib.import_module(module)
    return value if attr is None else getattr(value, attr)


def __dir__():
    return sorted(list(globals()) + list(_EXPORTS))
