"""The gated calibrator: the feedback while the model fits, else the anchor."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.calibrators.interface import Calibrator, CalStepOutput, run_calibrator
from jaxcal.calibrators.methods.policy.gated import (
    feedback_sensitivity,
    gate_threshold,
    make_gated_calibrator,
)
from jaxcal.calibrators.uncertainty.conformal import ThetaBand

S = 3
FEEDBACK_THETA, ANCHOR_THETA = 0.25, -0.5


def fake(theta: float, misfit) -> Calibrator:
    """A calibrator emitting ``theta`` and the prediction ``x - misfit(t)``."""

    def init(key, w0, x0):
        return jnp.zeros((), jnp.int32)

    def step(t, w, x):
        xhat = x - misfit(t) * jnp.ones_like(x)
        return t + 1, CalStepOutput(theta=jnp.full((1,), theta, x.dtype), xhat=xhat)

    return Calibrator(init, step)


def band(std: float) -> ThetaBand:
    return ThetaBand(edges=jnp.zeros((1,), jnp.int32), std=jnp.full((1, 1), std))


def run(misfit, *, window=2, own_band=None):
    # tau = J * 1.6449 * std = 10 * 1.6449 * 1e-3 ~ 0.016
    gated = make_gated_calibrator(
        fake(FEEDBACK_THETA, misfit),
        fake(ANCHOR_THETA, lambda t: 0.0),
        x_std=jnp.full((S,), 2.0),
        sensitivity=jnp.array([10.0]),
        anchor_band=band(1e-3),
        window=window,
        band=own_band,
    )
    T = 8
    w, x = jnp.zeros((T, 1)), jnp.ones((T, S))
    return jax.jit(lambda w, x: run_calibrator(gated, w, x))(w, x)


def test_threshold_is_the_residual_of_the_anchor_halfwidth():
    assert np.isclose(gate_threshold(jnp.array([3.0, 4.0]), jnp.array([1.0, 1.0])), 5)


def test_a_model_that_fits_keeps_the_feedback():
    out = run(lambda t: 0.0)
    np.testing.assert_array_equal(np.asarray(out.theta[:, 0]), FEEDBACK_THETA)
    assert np.asarray(out.aux["gate_open"]).all()
    assert np.asarray(out.valid).all()  # the gate's memory passes the state guard


def test_a_persistent_misfit_hands_over_to_the_anchor():
    out = run(lambda t: jnp.where(t >= 3, 1.0, 0.0))  # residual 0.5 from sample 3 on
    theta = np.asarray(out.theta[:, 0])
    np.testing.assert_array_equal(theta[:3], FEEDBACK_THETA)
    # one sample of misfit is tolerated (window 2), then the anchor
    np.testing.assert_array_equal(theta[3], FEEDBACK_THETA)
    np.testing.assert_array_equal(theta[4:], ANCHOR_THETA)
    np.testing.assert_allclose(np.asarray(out.aux["residual"])[4:], 0.5)


def test_a_single_spike_does_not_close_the_gate_and_a_window_of_one_does():
    spike = lambda t: jnp.where(t == 4, 1.0, 0.0)  # noqa: E731
    np.testing.assert_array_equal(np.asarray(run(spike).theta[:, 0]), FEEDBACK_THETA)
    theta = np.asarray(run(spike, window=1).theta[:, 0])
    assert theta[4] == ANCHOR_THETA and theta[5] == FEEDBACK_THETA


def test_a_failed_prediction_is_a_misfit_not_a_nan():
    out = run(lambda t: jnp.where(t >= 2, jnp.nan, 0.0))
    theta = np.asarray(out.theta[:, 0])
    assert np.isfinite(theta).all() and (theta[3:] == ANCHOR_THETA).all()


def test_the_std_is_the_own_band_while_open_and_the_anchors_when_closed():
    out = run(lambda t: jnp.where(t >= 3, 1.0, 0.0), own_band=band(2e-4))
    std = np.asarray(out.aux["theta_std"][:, 0])
    np.testing.assert_allclose(std[:4], 2e-4, rtol=1e-6)
    np.testing.assert_allclose(std[4:], 1e-3, rtol=1e-6)


def test_window_must_be_positive():
    with pytest.raises(ValueError, match="window"):
        run(lambda t: 0.0, window=0)


def test_sensitivity_inverts_the_step_reference():
    params = SimpleNamespace(
        step_ref=np.array([0.5 * 10.0 * 0.5 * 0.02]),  # n_ref = 0.5 J M, M = 0.5 width
        max_increment=0.5,
        theta_low=np.array([-0.02]),
        theta_high=np.array([0.0]),
    )
    np.testing.assert_allclose(feedback_sensitivity(params), [10.0])
    with pytest.raises(ValueError, match="incremental"):
        feedback_sensitivity(SimpleNamespace(step_ref=None))
