"""The turbofan engine model: ``load_engine(name).evaluate(w, theta) -> (x, info)``."""

from jaxcal.physics.engine import Engine, load_engine, make_engine
from jaxcal.physics.evaluation import EngineInfo, Envelope, evaluate_design

__all__ = [
    "Engine",
    "EngineInfo",
    "Envelope",
    "evaluate_design",
    "load_engine",
    "make_engine",
]
