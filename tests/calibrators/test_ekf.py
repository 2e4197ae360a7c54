"""The extended Kalman filter (jaxcal.calibrators.methods.ekf.filter) against the UKF.

On linear-Gaussian models, static and with memory, both filters are the exact Kalman
filter, so they must agree to round-off; on a nonlinear model the EKF must converge
about as well as the UKF. Missing outputs must give the update on the observed subset
and a box must hold the estimate. Float64 is on (tests/conftest.py).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.calibrators.interface import Measurement, run_calibrator
from jaxcal.calibrators.methods.ekf.filter import EKFConfig, make_ekf, make_joint_ekf
from jaxcal.calibrators.ukf import UKFConfig, make_joint_ukf, make_ukf
from jaxcal.problem import Transition

KEYS = ("theta_std", "innovation", "innovation_std", "log_likelihood")


def linear_static(w, theta):
    """x = A(w) theta + b(w): P = 2, S = 3."""
    a = jnp.stack([
        jnp.stack([1.0 + w[0], 0.5]),
        jnp.stack([w[1], 1.0 - w[0]]),
        jnp.stack([w[0] * w[1], 2.0]),
    ])  # fmt: skip
    return a @ theta + jnp.stack([w[0], -w[1], 0.3])


def linear_record(measure, theta_true, length, noise_std, seed):
    rng = np.random.default_rng(seed)
    w = rng.uniform(-1.0, 1.0, (length, 2))
    x = np.stack([np.asarray(measure(jnp.asarray(w_t), theta_true)) for w_t in w])
    return w, x + noise_std * rng.standard_normal(x.shape)


def assert_same(out_a, out_b, tol, keys=KEYS):
    np.testing.assert_allclose(out_a.theta, out_b.theta, rtol=0, atol=tol)
    np.testing.assert_allclose(out_a.xhat, out_b.xhat, rtol=0, atol=tol)
    for key in keys:
        np.testing.assert_allclose(out_a.aux[key], out_b.aux[key], rtol=0, atol=tol)


@pytest.mark.parametrize("posterior_xhat", [False, True])
def test_linear_static_equals_ukf(posterior_xhat):
    noise = np.array([0.05, 0.1, 0.2])
    w, x = linear_record(linear_static, jnp.array([0.7, -0.4]), 50, noise, seed=0)
    meas = Measurement(centre=jnp.array([0.1, 0.0, -0.2]), noise_std=jnp.asarray(noise))
    kw = dict(theta0=jnp.array([0.0, 0.5]), theta_scale=jnp.array([2.0, 0.5]))
    ekf = make_ekf(
        linear_static, EKFConfig(q=0.02, r=1.0, prior_std=1.5,
                                 posterior_xhat=posterior_xhat), meas, **kw,
    )  # fmt: skip
    ukf = make_ukf(
        linear_static, UKFConfig(q=0.02, r=1.0, prior_std=1.5,
                                 posterior_xhat=posterior_xhat), meas, **kw,
    )  # fmt: skip
    out_e, out_u = run_calibrator(ekf, w, x), run_calibrator(ukf, w, x)
    assert_same(out_e, out_u, 1e-9)
    # the filter moved: a vacuous agreement (both at the prior) would not count
    assert np.abs(out_e.theta[-1] - np.array([0.7, -0.4])).max() < 0.1


A_STATE = np.array([[0.8, 0.1], [-0.2, 0.6]])
B_THETA = np.array([[0.5, 0.0], [0.2, -0.3]])
C_OUT = np.array([[1.0, 0.0], [0.5, 1.0], [0.0, -1.0]])
D_THETA = np.array([[0.0, 0.2], [0.0, 0.0], [0.4, 0.0]])


def linear_step(z, w, theta):
    z_next = A_STATE @ z + B_THETA @ theta + jnp.stack([w[0], w[0] * w[1]])
    return z_next, C_OUT @ z_next + D_THETA @ theta


def linear_init(w0, theta):
    return jnp.stack([theta[0] + w0[0], -theta[1]])


def memory_record(theta_true, length, noise_std, seed):
    rng = np.random.default_rng(seed)
    w = rng.uniform(-1.0, 1.0, (length, 2))
    z = linear_init(jnp.asarray(w[0]), theta_true)
    xs = []
    for w_t in w:
        z, x = linear_step(z, jnp.asarray(w_t), theta_true)
        xs.append(np.asarray(x))
    return w, np.stack(xs) + noise_std * rng.standard_normal((length, 3))


@pytest.mark.parametrize("posterior_xhat", [False, True])
def test_linear_memory_equals_joint_ukf(posterior_xhat):
    noise = np.array([0.05, 0.05, 0.1])
    w, x = memory_record(jnp.array([0.6, -0.5]), 50, noise, seed=1)
    meas = Measurement(centre=jnp.zeros(3), noise_std=jnp.asarray(noise))
    transition = Transition(linear_init, linear_step, 2)
    kw = dict(
        theta0=jnp.array([0.0, 0.0]), theta_scale=jnp.array([1.0, 2.0]),
        state_std=jnp.array([0.3, 0.1]), state_q=jnp.array([0.02, 0.05]),
        state_scale=jnp.array([1.0, 0.5]),
    )  # fmt: skip
    settings = dict(q=0.01, r=1.0, prior_std=1.0, posterior_xhat=posterior_xhat)
    ekf = make_joint_ekf(transition, EKFConfig(**settings), meas, **kw)
    ukf = make_joint_ukf(transition, UKFConfig(**settings), meas, **kw)
    out_e, out_u = run_calibrator(ekf, w, x), run_calibrator(ukf, w, x)
    assert_same(out_e, out_u, 1e-9, KEYS + ("state", "state_std"))
    assert np.abs(out_e.theta[-1] - np.array([0.6, -0.5])).max() < 0.1


def nonlinear_static(w, theta):
    return jnp.stack(
        [jnp.exp(theta[0] * w[0]), theta[0] * theta[1], jnp.sin(theta[1]) + w[0]]
    )


def test_nonlinear_converges_like_ukf():
    theta_true, theta0 = jnp.array([0.8, 1.3]), jnp.array([0.5, 1.0])
    rng = np.random.default_rng(2)
    w = rng.uniform(0.0, 1.5, (300, 1))
    x = jax.vmap(nonlinear_static, (0, None))(jnp.asarray(w), theta_true)
    x = np.asarray(x) + 0.01 * rng.standard_normal(x.shape)
    meas = Measurement(centre=jnp.zeros(3), noise_std=jnp.full((3,), 0.01))
    settings = dict(q=1e-3, r=1.0, prior_std=0.5)
    rmse = {}
    for name, make, cfg in (
        ("ekf", make_ekf, EKFConfig(**settings)),
        ("ukf", make_ukf, UKFConfig(**settings)),
    ):
        out = run_calibrator(make(nonlinear_static, cfg, meas, theta0=theta0), w, x)
        err = np.asarray(out.theta[150:]) - np.asarray(theta_true)
        rmse[name] = np.sqrt(np.mean(err**2))
    prior_error = np.sqrt(np.mean((theta0 - theta_true) ** 2))
    assert rmse["ekf"] < 1.5 * rmse["ukf"], rmse
    assert max(rmse.values()) < 0.05 * prior_error, rmse


def test_missing_output_is_the_observed_subset_update():
    """A row with output 1 missing updates exactly as the EKF of the model without
    output 1 does from the same state; the run stays finite and reports 0 innovation
    there."""
    noise = np.array([0.05, 0.1, 0.2])
    w, x = linear_record(linear_static, jnp.array([0.7, -0.4]), 20, noise, seed=3)
    x[10, 1] = np.nan
    keep = np.array([0, 2])
    meas = Measurement(centre=jnp.zeros(3), noise_std=jnp.asarray(noise))
    sub_meas = Measurement(centre=jnp.zeros(2), noise_std=jnp.asarray(noise[keep]))
    cfg, theta0 = EKFConfig(q=0.02, r=1.0), jnp.zeros(2)
    full = make_ekf(linear_static, cfg, meas, theta0=theta0)
    sub = make_ekf(lambda w_t, th: linear_static(w_t, th)[keep], cfg, sub_meas,
                   theta0=theta0)  # fmt: skip
    out = run_calibrator(full, w, x)
    assert bool(out.valid.all()) and bool(out.partial[10])
    assert np.isfinite(np.asarray(out.theta)).all()
    assert out.aux["innovation"][10, 1] == 0.0

    full_step, sub_step = jax.jit(full.step), jax.jit(sub.step)
    state = full.init(None, jnp.asarray(w[0]), jnp.asarray(x[0]))
    for t in range(10):  # the state before the partial row, step by step
        state, _ = full_step(state, jnp.asarray(w[t]), jnp.asarray(x[t]))
    got_state, got = full_step(state, jnp.asarray(w[10]), jnp.asarray(x[10]))
    want_state, want = sub_step(state, jnp.asarray(w[10]), jnp.asarray(x[10, keep]))
    np.testing.assert_allclose(got_state.mean, want_state.mean, atol=1e-12)
    np.testing.assert_allclose(got_state.cov, want_state.cov, atol=1e-12)
    np.testing.assert_allclose(got.aux["innovation"][keep], want.aux["innovation"])
    np.testing.assert_allclose(got.aux["log_likelihood"], want.aux["log_likelihood"])
    np.testing.assert_allclose(out.theta[10], got.theta, atol=1e-12)


def test_estimate_stays_in_box():
    """The truth lies outside the box: the static and the joint EKF's estimates stay
    inside it and end at the violated bound."""
    low, high = np.array([-1.0, -0.3]), np.array([1.0, 1.0])
    noise = np.array([0.05, 0.1, 0.2])
    theta_true = jnp.array([0.7, -0.8])
    w, x = linear_record(linear_static, theta_true, 60, noise, seed=4)
    meas = Measurement(centre=jnp.zeros(3), noise_std=jnp.asarray(noise))
    cfg = EKFConfig(q=0.02, r=1.0, prior_std=2.0)
    out = run_calibrator(
        make_ekf(linear_static, cfg, meas, theta0=jnp.zeros(2), theta_box=(low, high)),
        w, x,
    )  # fmt: skip
    w_m, x_m = memory_record(theta_true, 60, np.full(3, 0.05), seed=5)
    joint = make_joint_ekf(
        Transition(linear_init, linear_step, 2), cfg,
        Measurement(centre=jnp.zeros(3), noise_std=jnp.full(3, 0.05)),
        theta0=jnp.zeros(2), theta_box=(low, high),
    )  # fmt: skip
    out_m = run_calibrator(joint, w_m, x_m)
    for theta in (np.asarray(out.theta), np.asarray(out_m.theta)):
        assert np.isfinite(theta).all()
        assert (theta >= low).all() and (theta <= high).all()
        assert theta[-1, 1] == pytest.approx(low[1], abs=1e-3)


@pytest.mark.parametrize("field", ["q", "r", "prior_std"])
def test_config_rejects_nonpositive(field):
    with pytest.raises(ValueError, match=f"EKFConfig.{field} must be > 0"):
        EKFConfig(**{field: 0.0})
    with pytest.raises(ValueError, match="EKFConfig.jitter must be >= 0"):
        EKFConfig(jitter=-1.0)
