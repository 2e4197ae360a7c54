"""jaxcal: real-time calibration of physics-based models in JAX.

The public front::

    import jaxcal

    model = jaxcal.Model.from_function(fn, conditions=..., parameters=..., outputs=...)
    result = jaxcal.calibrate(model, "data.csv", method="ukf")  # or "ls", "e2e"
    turbofan = jaxcal.models.load("cmapss")
    data = jaxcal.read_dataset("data.parquet", model)           # a jaxcal.Dataset

Layers (imports flow one way): ``model`` / ``problem`` -> ``physics`` / ``models`` ->
``data`` -> ``surrogate`` -> ``envs`` -> ``agents`` / ``baselines`` / ``calibrators``
-> ``training`` -> ``evaluation`` / ``loop`` / ``fleet`` -> CLI modules. Importing the
package has no side effects and loads nothing heavy: the names below are imported on
first use, and float64 is switched on only by entry points
(:func:`jaxcal.precision.enable_x64`).
"""

import importlib

__version__ = "0.1.0"

_EXPORTS = {
    "Model": ("jaxcal.model", "Model"),
    "Parameter": ("jaxcal.model", "Parameter"),
    "Variable": ("jaxcal.model", "Variable"),
    "Problem": ("jaxcal.problem", "Problem"),
    "Dataset": ("jaxcal.data.dataset", "Dataset"),
    "read_dataset": ("jaxcal.data.readers", "read_dataset"),
    "calibrate": ("jaxcal.calibrators.front", "calibrate"),
    "CalibrationResult": ("jaxcal.calibrators.result", "CalibrationResult"),
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
