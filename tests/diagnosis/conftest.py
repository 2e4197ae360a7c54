"""Shared fixtures of the diagnosis tests: one turbofan model, cached small data sets.

Every turbofan test goes through the one jitted linearisation of
:mod:`jaxcal.diagnosis.effects` (fixed chunk shape), so the engine compiles once per
session.
"""

import functools

import jax
import pytest

from jaxcal.diagnosis.data.synthetic import SyntheticConfig, make_synthetic_data
from jaxcal.models import load
from jaxcal.models.turbofan.scenario import (
    DISCREPANCY_BUMP,
    EFFECT_SIZES,
    STUDY_OUTPUTS,
    ScenarioConfig,
    make_scenario,
)

DECLARED = ("HPT_eff_mod",)
# Two units, every other cycle, two samples per flight: ~150 rows, one engine chunk.
SMALL = ScenarioConfig(num_units=2, rows_per_cycle=2, cycle_stride=2, declared=DECLARED)
STUDY = SyntheticConfig(
    sensors=STUDY_OUTPUTS,
    declared=DECLARED,
    sizes=EFFECT_SIZES,
    parameter_physical=True,
    bump=DISCREPANCY_BUMP,
)


@pytest.fixture(scope="session")
def study_config():
    """The study's synthetic settings (a fixture: ``from conftest import`` picks
    whichever conftest module the run imported first)."""
    return STUDY


@pytest.fixture(scope="session")
def engine():
    """The ``cmapss`` turbofan as a :class:`jaxcal.Model`."""
    return load("cmapss")


@pytest.fixture(scope="session")
def synthetic(engine):
    """``synthetic(kind, seed=0, target=None, size=None)``: a cached data set."""

    @functools.cache
    def make(kind, seed=0, target=None, size=None):
        key = jax.random.fold_in(jax.random.key(seed), 7)
        return make_synthetic_data(
            key, engine, kind, STUDY, make_scenario(SMALL), target=target, size=size
        )

    return make


@pytest.fixture
def evaluated_rows(monkeypatch):
    """The row counts the model is linearised at (:func:`jaxcal.diagnosis.
    linearization.linearize`, its cache of recent points emptied first)."""
    import jaxcal.diagnosis.kinds.linearization as linearization

    calls = []
    original = linearization.linearize

    def counted(model, w, *args, **kwargs):
        calls.append(w.shape[0])
        return original(model, w, *args, **kwargs)

    monkeypatch.setattr(linearization, "linearize", counted)
    monkeypatch.setattr(linearization, "_LINEARIZED", type(linearization._LINEARIZED)())
    return calls
