"""Fixtures shared by the table tests."""

import jax.numpy as jnp
import pytest

import jaxcal


@pytest.fixture(scope="module")
def model():
    """Two conditions (a, b), one parameter p, two outputs: y1 = a p, y2 = b + p."""
    return jaxcal.Model.from_function(
        lambda w, t: jnp.stack([w[0] * t[0], w[1] + t[0]]),
        conditions=("a", "b"),
        parameters={"p": (1.0, 0.5, 2.0)},
        outputs=("y1", "y2"),
    )
