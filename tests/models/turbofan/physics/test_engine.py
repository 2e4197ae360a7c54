"""The engine's contract: interface, jit/vmap/grad, bad input, conservation."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.audit import audit_point
from jaxcal.models.turbofan.physics.constants import (
    HEALTH_NAMES,
    MEASURED_SENSOR_NAMES,
    SENSOR_NAMES,
    VIRTUAL_SENSOR_NAMES,
)
from jaxcal.models.turbofan.physics.engine import load_engine

CRUISE = np.array([35000.0, 0.78, 85.0, float(isa_total_temperature(35000.0, 0.78))])
SLS = np.array([0.0, 0.0, 100.0, 518.67])


def test_interface_names(cmapss):
    assert cmapss.condition_names == ("alt", "Mach", "TRA", "T2")
    assert cmapss.health_names == HEALTH_NAMES
    assert cmapss.sensor_names[:14] == MEASURED_SENSOR_NAMES
    assert cmapss.sensor_names[14:28] == VIRTUAL_SENSOR_NAMES
    assert cmapss.sensor_names[28:] == (
        "epr", "NRf", "NRc", "BPR", "farB", "PCNfR_dmd", "Nf_dmd",
    )  # fmt: skip
    with pytest.raises(ValueError, match="unknown engine"):
        load_engine("boeing")


# one eager evaluation of a broadcast batch, shared: the eager path compiles the
# solver's loop for its shapes (the longest part of these tests)
W2 = np.stack([SLS, CRUISE])[:, None, :]  # [2, 1, 4]
TH3 = np.zeros((3, 10))
TH3[1, 6] = -0.01


@pytest.fixture(scope="module")
def eager(cmapss):
    """``cmapss.evaluate(W2, TH3)`` on the eager path: ``(x [2, 3, S], info)``."""
    return cmapss.evaluate(W2, TH3)


def test_any_batch_shape_and_broadcasting(evaluate, eager):
    w = W2[:, 0]
    x2, info2 = evaluate(w, np.zeros(10))
    assert x2.shape == (2, len(SENSOR_NAMES)) and info2.converged.all()
    # [2, 1, 4] x [3, 10] -> [2, 3, S], eager path, same numbers
    x3, info3 = eager
    assert x3.shape == (2, 3, len(SENSOR_NAMES)) and info3.converged.shape == (2, 3)
    np.testing.assert_allclose(np.asarray(x3)[:, 0], x2, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(x3)[:, 2], x2, rtol=1e-10)


def test_jit_equals_eager_and_compiles_once(eager, cmapss):
    chex.clear_trace_counter()
    f = jax.jit(chex.assert_max_traces(cmapss.evaluate, n=1))
    x_jit, _ = f(W2, TH3)
    x_jit2, _ = f(W2 + [100.0, 0, 0, 0], TH3)  # same shapes: no retrace
    np.testing.assert_allclose(x_jit, eager[0], rtol=1e-10)
    assert not np.allclose(x_jit, x_jit2)


def test_vmap_matches_batch(cmapss, evaluate):
    w = np.stack([SLS, CRUISE, CRUISE])
    th = np.zeros((3, 10))
    th[2, 6] = -0.01
    x_b, _ = evaluate(w, th)
    x_v, _ = jax.jit(jax.vmap(cmapss.evaluate))(w, th)
    np.testing.assert_allclose(x_v, x_b, rtol=1e-10)


def test_conservation_closes(cmapss, evaluate):
    w = np.stack([SLS, CRUISE, [20000.0, 0.5, 30.0, 470.0]])
    th = np.zeros((3, 10))
    th[1, 4:] = -0.02
    th[2, 0:2] = -0.1
    _, info = evaluate(w, th)
    assert info.converged.all()
    audit = jax.jit(
        jax.vmap(lambda a, b, z: audit_point(cmapss.design, a, b, jnp.zeros(6), z))
    )
    for value in audit(w, th, info.z):
        assert float(jnp.max(value)) < 1e-8


def test_health_modifiers_move_the_right_sensors(evaluate):
    w = np.stack([CRUISE, CRUISE])
    th = np.zeros((2, 10))
    th[1, 6] = -0.01  # HPT efficiency loss at fixed fan speed (physics_facts.md 3.2)
    x, _ = evaluate(w, th)
    d = x[1] - x[0]
    s = SENSOR_NAMES.index
    assert d[s("T48")] > 5 and d[s("T50")] > 5 and d[s("Wf")] > 0 and d[s("Nc")] < 0
    assert d[s("Nf")] == pytest.approx(
        0.0, abs=1e-9
    )  # the controller holds the fan speed


def test_gradients_match_finite_differences(cmapss, evaluate):
    names = ("T48", "T30", "Ps30", "Nc", "Wf")
    idx = np.array([SENSOR_NAMES.index(n) for n in names])

    def xs(w, th):
        return cmapss.evaluate(w, th)[0][idx]

    th0 = np.full(10, -0.004)
    jt, jw = jax.jit(jax.jacfwd(xs, argnums=(1, 0)))(
        jnp.asarray(CRUISE), jnp.asarray(th0)
    )
    # central differences through the shared compiled evaluate (one batch of 10 rows)
    cols, h_th, h_tra = (0, 4, 6, 9), 1e-6, 1e-4
    w = np.tile(CRUISE, (10, 1))
    th = np.tile(th0, (10, 1))
    for k, j in enumerate(cols):
        th[2 * k, j] += h_th
        th[2 * k + 1, j] -= h_th
    w[8, 2] += h_tra
    w[9, 2] -= h_tra
    x, info = evaluate(w, th)
    assert info.converged.all()
    x = x[:, idx]
    for k, j in enumerate(cols):
        fd = (x[2 * k] - x[2 * k + 1]) / (2 * h_th)
        np.testing.assert_allclose(
            jt[:, j], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max()
        )
    np.testing.assert_allclose(jw[:, 2], (x[8] - x[9]) / (2 * h_tra), rtol=1e-5)
    # reverse mode goes through the same implicit-function rule
    g = jax.jit(jax.grad(lambda t: xs(jnp.asarray(CRUISE), t)[0]))(jnp.asarray(th0))
    np.testing.assert_allclose(g, jt[0], rtol=1e-8)


def test_bad_input_is_flagged_never_silent(evaluate, cmapss):
    w = np.stack([[np.nan, 0.7, 80.0, 430.0], [60000.0, 0.8, 80.0, 400.0], CRUISE])
    th = np.zeros((3, 10))
    th[2, 6] = -0.5  # far outside the envelope
    x, info = evaluate(w, th)
    assert not info.converged.any()
    assert not info.in_envelope.any()
    # no NaN without the flag: every non-finite output row is flagged
    assert np.all(info.converged | ~np.isfinite(x).all(axis=1) | ~info.in_envelope)


@pytest.mark.parametrize(
    "w,theta,match",
    [
        ([np.nan, 0.7, 80.0, 430.0], np.zeros(10), r"w\[\.\.\., 'alt'\]"),
        ([30000.0, 1.5, 80.0, 480.0], np.zeros(10), r"'Mach'.*\[0\.0, 0\.9\]"),
        ([30000.0, 0.7, 150.0, 430.0], np.zeros(10), r"'TRA'"),
        ([30000.0, 0.7, 80.0, 600.0], np.zeros(10), r"T2 - T2_ISA"),
        (
            CRUISE,
            np.eye(10)[6] * -0.5,
            r"theta\[\.\.\., 'HPT_eff_mod'\].*\[-0\.1, 0\.03\]",
        ),
    ],
)
def test_evaluate_checked_names_the_field(cmapss, w, theta, match):
    with pytest.raises(ValueError, match=match):
        cmapss.evaluate_checked(np.asarray(w), theta)


def test_evaluate_checked_rejects_bad_shapes(cmapss):
    with pytest.raises(ValueError, match=r"w must have shape \[\.\.\., 4\]"):
        cmapss.evaluate_checked(np.zeros(3), np.zeros(10))
    with pytest.raises(ValueError, match=r"theta must have shape \[\.\.\., 10\]"):
        cmapss.evaluate_checked(CRUISE, np.zeros(9))
