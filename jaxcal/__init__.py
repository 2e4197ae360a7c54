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
``calibrators/`` (the methods and the front door) -> ``training/`` (the job and its
config) -> ``deploy/`` (loading a run, streaming) -> ``diagnosis/`` / ``fleet/`` /
``paper/`` -> ``cli/`` (every ``python -m jaxcal.<tool>``; the old module paths are
shims that forward there). Importing the package loads nothing heavy: the names below
are imported on first use, and float64 is switched on only by entry points
(:func:`jaxcal.precision.enable_x64`).

This module is the composition root. Its acts at import: it hands the run-folder
slot of :mod:`jaxcal.runs` the reader of :mod:`jaxcal.deploy.loading` (imported when a
run is first read), so the policy method and the front door, below the training
layer, take a run folder without importing a layer above their own; likewise it
hands the turbofan's files (N-CMAPSS, C-MAPSS) to :data:`jaxcal.data.FILE_READERS` and
:data:`jaxcal.training.data.MODEL_FILES`: the core imports nothing of the turbofan.
"""

import importlib

from jaxcal import data as _data
from jaxcal import runs as _runs
from jaxcal.training import data as _training_data
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


def _lazy(module: str, name: str):
    """``module.name``, imported on first call."""
    return lambda *args, **kwargs: getattr(importlib.import_module(module), name)(
        *args, **kwargs
    )


_runs.register_run_reader(_lazy("jaxcal.deploy.loading", "load_run"))
_read_file = _lazy("jaxcal.models.turbofan.data.datasets", "read_file")
_data.FILE_READERS.update(dict.fromkeys((".h5", ".hdf5", ".txt"), _read_file))
_training_data.MODEL_FILES.update(
    read=_lazy("jaxcal.models.turbofan.training", "read_data"),
    generator=_lazy("jaxcal.models.turbofan.training", "generator"),
)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'jaxcal' has no attribute {name!r}")
    module, attr = _EXPORTS[name]
    value = importlib.import_module(module)
    return value if attr is None else getattr(value, attr)


def __dir__():
    return sorted(list(globals()) + list(_EXPORTS))
