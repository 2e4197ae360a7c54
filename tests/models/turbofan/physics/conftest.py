"""Shared engine fixtures: one jitted evaluate of a fixed batch size per configuration.

Compiling the engine costs ~10-30 s on this machine, so every test pads its points to
``BATCH`` rows and calls the same compiled function.
"""

import jax
import numpy as np
import pytest

from jaxcal.models.turbofan.physics.engine import load_engine

BATCH = 16


@pytest.fixture(scope="session")
def cmapss():
    return load_engine("cmapss")


@pytest.fixture(scope="session")
def evaluate(cmapss):
    """evaluate(w [n,4], theta [n,10]) -> (x [n,S], info) through one compiled
    program."""
    f = jax.jit(cmapss.evaluate)

    def run(w, theta):
        w = np.atleast_2d(np.asarray(w, float))
        theta = np.broadcast_to(np.asarray(theta, float), (len(w), 10))
        n = len(w)
        assert n <= BATCH
        pad = BATCH - n
        wp = np.concatenate([w, np.repeat(w[-1:], pad, 0)])
        tp = np.concatenate([theta, np.repeat(theta[-1:], pad, 0)])
        x, info = f(wp, tp)
        return np.asarray(x)[:n], jax.tree.map(lambda a: np.asarray(a)[:n], info)

    return run
