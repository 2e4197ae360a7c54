"""The turbofan engine model: ``load_engine(name).evaluate(w, theta) -> (x, info)``.

The names are imported on first use (PEP 562): a module that needs only
:mod:`jaxcal.physics.constants` (the calibrators' sensor and health indices) does not
pay for the engine and its imports, about 0.3 s of every new process that calibrates
a model of its own."""

import importlib

_WHERE = {
    "Engine": "jaxcal.physics.engine",
    "load_engine": "jaxcal.physics.engine",
    "make_engine": "jaxcal.physics.engine",
    "EngineInfo": "jaxcal.physics.evaluation",
    "Envelope": "jaxcal.physics.evaluation",
    "evaluate_design": "jaxcal.physics.evaluation",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module 'jaxcal.physics' has no attribute {name!r}")
    value = getattr(importlib.import_module(_WHERE[name]), name)
    globals()[name] = value  # looked up once
    return value


def __dir__():
    return sorted((*globals(), *_WHERE))
