"""The newcomer's reactor (``experiments/reactor.py``: a CSTR with two hidden states,
RK4 sub-steps, catalyst activity falling) at test size.

The model and its fleet live in the experiment, the one definition; this module
loads that file (``experiments`` is no package) and draws small fleets of it.
"""

import importlib.util
import pathlib

_PATH = pathlib.Path(__file__).resolve().parents[2] / "experiments" / "reactor.py"
_SPEC = importlib.util.spec_from_file_location("jaxcal_experiments_reactor", _PATH)
reactor = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(reactor)

THETA = reactor.THETA
NOISE = reactor.NOISE
MODEL = reactor.reactor_model()


def small_fleet(seed: int = 0, *, units: int = 3, rows: int = 300, **scenario):
    """``units`` units of ``rows`` samples of the reactor (``scenario``: ``phi``,
    ``bias``, ``bias_units``, ``bias_from``, as :func:`reactor.make_fleet`)."""
    return reactor.make_fleet(seed, units=units, rows=rows, **scenario)
