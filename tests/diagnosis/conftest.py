"""Shared fixtures of the closing-the-loop tests: one engine, cached small records.

Every engine-based test goes through the one jitted linearisation of
:mod:`jaxcal.diagnosis.effects` (fixed chunk shape), so the engine compiles once per session.
"""

import functools

import jax
import pytest

from jaxcal.diagnosis.synthetic import SyntheticConfig, make_synthetic_record
from jaxcal.physics import load_engine

DECLARED = ("HPT_eff_mod",)
# Two units, every other cycle, two samples per flight: ~150 rows, one engine chunk.
SMALL = SyntheticConfig(
    num_units=2, rows_per_cycle=2, cycle_stride=2, declared=DECLARED
)


@pytest.fixture(scope="session")
def engine():
    return load_engine("cmapss")


@pytest.fixture(scope="session")
def synthetic(engine):
    """``synthetic(kind, seed=0, target=None, size=None)``: a cached record."""

    @functools.cache
    def make(kind, seed=0, target=None, size=None):
        key = jax.random.fold_in(jax.random.key(seed), 7)
        return make_synthetic_record(key, engine, kind, SMALL, target=target, size=size)

    return make
