"""UKF: exact on linear-Gaussian models, tracks nonlinear drift, compiles once."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.kalman import kalman_filter

from jaxcal.calibrators.interface import Measurement, run_calibrator
from jaxcal.calibrators.ukf import (
    UKFConfig,
    make_ukf,
    sigma_points,
    ukf_filter,
    unscented_weights,
)

NUM_STEPS, NUM_PARAMS, NUM_SENSORS, NUM_CONDITIONS = 25, 3, 4, 2


def _linear_problem(seed=0):
    rng = np.random.default_rng(seed)
    obs_matrix = rng.normal(size=(NUM_SENSORS, NUM_PARAMS))
    cond_matrix = rng.normal(size=(NUM_SENSORS, NUM_CONDITIONS))
    meas = Measurement(
        centre=jnp.asarray(rng.normal(size=NUM_SENSORS)),
        noise_std=jnp.asarray(rng.uniform(0.5, 2.0, NUM_SENSORS)),
    )
    w = rng.normal(size=(NUM_STEPS, NUM_CONDITIONS))
    theta = 0.3 + np.cumsum(0.05 * rng.normal(size=(NUM_STEPS, NUM_PARAMS)), axis=0)
    x = (
        theta @ obs_matrix.T
        + w @ cond_matrix.T
        + 0.05 * rng.normal(size=(NUM_STEPS, 4))
    )

    def measure(w_t, theta_t):
        return jnp.asarray(obs_matrix) @ theta_t + jnp.asarray(cond_matrix) @ w_t

    return measure, obs_matrix, cond_matrix, meas, jnp.asarray(w), jnp.asarray(x)


@pytest.mark.parametrize(
    "alpha,beta,kappa,jitter", [(1.0, 2.0, 0.0, 1e-10), (0.5, 2.0, 1.0, 0.0)]
)
def test_ukf_matches_kalman_filter_on_linear_model(alpha, beta, kappa, jitter):
    measure, obs_matrix, cond_matrix, meas, w, x = _linear_problem()
    scale = jnp.array([0.5, 2.0, 1.0])
    theta0 = jnp.array([0.1, -0.2, 0.0])
    cfg = UKFConfig(
        q=0.05, r=0.1, prior_std=0.7, alpha=alpha, beta=beta, kappa=kappa,
        jitter=jitter, return_cov=True,
    )  # fmt: skip
    out = ukf_filter(measure, w, x, meas, cfg, theta0=theta0, theta_scale=scale)
    # Cholesky jitter (scaled units) is the only deliberate departure from exactness.
    cov_atol = 1e-12 + 10 * jitter * float(jnp.max(scale)) ** 2

    # The same model written for the exact filter, in theta units and normalised y.
    y = (x - meas.centre) / meas.noise_std
    h_n = jnp.asarray(obs_matrix) / meas.noise_std[:, None]
    b_n = (w @ jnp.asarray(cond_matrix).T - meas.centre) / meas.noise_std
    ref = kalman_filter(
        y, h_n, b_n,
        jnp.diag((cfg.q * scale) ** 2), cfg.r**2 * jnp.eye(NUM_SENSORS),
        theta0, jnp.diag((cfg.prior_std * scale) ** 2),
    )  # fmt: skip

    np.testing.assert_allclose(out.theta, ref.mean, atol=1e-8, rtol=0)
    np.testing.assert_allclose(out.aux["theta_cov"], ref.cov, atol=cov_atol, rtol=0)
    np.testing.assert_allclose(
        out.aux["theta_std"],
        jnp.sqrt(jnp.diagonal(ref.cov, axis1=1, axis2=2)),
        atol=1e-9,
    )
    np.testing.assert_allclose(out.aux["log_likelihood"], ref.log_likelihood, atol=1e-8)
    np.testing.assert_allclose(out.aux["innovation"], y - ref.y_pred, atol=1e-8, rtol=0)
    np.testing.assert_allclose(
        out.xhat, ref.mean @ obs_matrix.T + w @ cond_matrix.T, atol=1e-8
    )


def test_sigma_points_reproduce_mean_and_covariance():
    cfg = UKFConfig(alpha=0.8, kappa=1.0)
    mean = jnp.array([1.0, -2.0, 0.5])
    a = jnp.array([[1.0, 0.2, 0.0], [0.3, 0.5, 0.1], [0.0, -0.4, 2.0]])
    cov = a @ a.T
    wm, wc, spread = unscented_weights(3, cfg)
    points = sigma_points(mean, cov, spread, 0.0)
    chex.assert_shape(points, (7, 3))
    np.testing.assert_allclose(wm @ points, mean, atol=1e-12)
    d = points - mean
    np.testing.assert_allclose(d.T @ (wc[:, None] * d), cov, atol=1e-12)


def _toy_measure(w_t, theta_t):
    """A smooth nonlinear model with 2 parameters, 5 sensors, 1 condition."""
    a = jnp.array([1.0, 0.5, -0.8, 0.3, 1.2])
    b = jnp.array([0.2, -1.0, 0.4, 0.9, -0.3])
    return jnp.exp(a * theta_t[0]) * (1.0 + w_t[0]) + jnp.tanh(b * theta_t[1] + w_t[0])


def _drifting_record(num_steps, seed, noise=0.002):
    rng = np.random.default_rng(seed)
    t = np.arange(num_steps)
    theta = np.stack([0.2 - 0.004 * t, -0.3 + 0.003 * t], axis=1)
    w = rng.uniform(-0.5, 0.5, (num_steps, 1))
    x = jax.vmap(_toy_measure)(jnp.asarray(w), jnp.asarray(theta))
    x = x + noise * rng.normal(size=x.shape)
    return jnp.asarray(w), x, theta


def test_ukf_tracks_slowly_drifting_nonlinear_parameters_fleet():
    num_steps = 120
    records = [_drifting_record(num_steps, seed) for seed in (0, 1)]
    w = jnp.stack([r[0] for r in records])
    x = jnp.stack([r[1] for r in records])
    theta = np.stack([r[2] for r in records])
    meas = Measurement(centre=jnp.zeros(5), noise_std=jnp.full(5, 0.1))
    cfg = UKFConfig(q=0.05, r=0.02, prior_std=1.0)
    out = ukf_filter(_toy_measure, w, x, meas, cfg, theta0=jnp.zeros(2), unroll=4)
    chex.assert_shape(out.theta, (2, num_steps, 2))
    chex.assert_tree_all_finite(out)
    err = np.abs(np.asarray(out.theta) - theta)[:, 30:]
    assert err.max() < 0.015, err.max()
    # The filter's own uncertainty is honest: errors mostly within 3 posterior stds.
    assert np.mean(err < 3 * np.asarray(out.aux["theta_std"])[:, 30:]) > 0.9
    # Tracking: the posterior output follows the measurements to the noise level.
    resid = np.asarray(out.xhat - x)[:, 30:]
    assert np.sqrt(np.mean(resid**2)) < 0.01


def test_ukf_step_eager_equals_jit():
    w, x, _ = _drifting_record(3, seed=2)
    meas = Measurement(centre=jnp.zeros(5), noise_std=jnp.ones(5))
    ukf = make_ukf(_toy_measure, UKFConfig(), meas, theta0=jnp.zeros(2))
    state = ukf.init(None, w[0], x[0])
    eager = ukf.step(state, w[0], x[0])
    chex.assert_trees_all_close(eager, jax.jit(ukf.step)(state, w[0], x[0]), atol=1e-12)


def test_ukf_step_compiles_once():
    w, x, _ = _drifting_record(3, seed=3)
    meas = Measurement(centre=jnp.zeros(5), noise_std=jnp.ones(5))
    ukf = make_ukf(_toy_measure, UKFConfig(), meas, theta0=jnp.zeros(2))
    chex.clear_trace_counter()
    step = jax.jit(chex.assert_max_traces(ukf.step, n=1))
    state = ukf.init(None, w[0], x[0])
    for t in range(3):
        state, _ = step(state, w[t], x[t])
    chex.assert_tree_all_finite(state)


def test_masked_rows_hold_the_filter():
    w, x, _ = _drifting_record(10, seed=4)
    meas = Measurement(centre=jnp.zeros(5), noise_std=jnp.ones(5))
    ukf = make_ukf(_toy_measure, UKFConfig(), meas, theta0=jnp.zeros(2))
    run = jax.jit(run_calibrator, static_argnums=0)
    full = run(ukf, w, x, jnp.ones(10, bool))
    out = run(ukf, w, x, jnp.arange(10) < 6)  # trailing padding, as in [U, T] data
    np.testing.assert_allclose(out.theta[:6], full.theta[:6], atol=1e-12)
    np.testing.assert_allclose(out.theta[6:], jnp.tile(full.theta[5], (4, 1)))
    np.testing.assert_allclose(out.aux["theta_std"][9], full.aux["theta_std"][5])


def test_bad_inputs_raise_clear_errors():
    meas = Measurement(centre=jnp.zeros(5), noise_std=jnp.ones(5))
    with pytest.raises(ValueError, match="q"):
        UKFConfig(q=0.0)
    with pytest.raises(ValueError, match="std"):
        make_ukf(
            _toy_measure,
            UKFConfig(),
            Measurement(jnp.zeros(5), jnp.zeros(5)),
            theta0=jnp.zeros(2),
        )
    with pytest.raises(ValueError, match="theta_scale"):
        make_ukf(
            _toy_measure,
            UKFConfig(),
            meas,
            theta0=jnp.zeros(2),
            theta_scale=jnp.ones(3),
        )
    with pytest.raises(ValueError, match="sensors"):
        ukf_filter(
            _toy_measure,
            jnp.zeros((4, 1)),
            jnp.zeros((4, 3)),
            meas,
            theta0=jnp.zeros(2),
        )
