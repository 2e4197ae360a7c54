"""Least squares: exact recovery, honest covariance, step tracking, one trace."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.calibrators.interface import Measurement, run_calibrator
from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig, make_least_squares
from tests.support.ls_fit import FitConfig, fit_least_squares

TRUTH = jnp.array([0.4, -0.7, 0.2])


def _toy_measure(w_t, theta):
    """Nonlinear, identifiable: 3 parameters, 4 sensors, 1 condition."""
    w = w_t[0]
    return jnp.stack([
        jnp.exp(theta[0] * w),
        theta[1] * jnp.sin(2.0 * w) + theta[0] ** 2,
        jnp.tanh(theta[2] + theta[1] * w),
        theta[2] * w**2 + theta[0] * theta[1],
    ])  # fmt: skip


def _record(theta_seq, seed, noise=0.0):
    rng = np.random.default_rng(seed)
    w = jnp.asarray(rng.uniform(-1.0, 1.0, (theta_seq.shape[0], 1)))
    x = jax.vmap(_toy_measure)(w, theta_seq)
    return w, x + noise * jnp.asarray(rng.normal(size=x.shape))


def test_fit_recovers_known_parameters_from_noise_free_data():
    w, x = _record(jnp.tile(TRUTH, (25, 1)), seed=0)
    theta, info = fit_least_squares(_toy_measure, w, x, jnp.array([0.1, 0.1, 0.1]))
    np.testing.assert_allclose(theta, TRUTH, atol=1e-8, rtol=0)
    assert bool(info.converged)
    assert float(info.cost) < 1e-20
    assert 0 < int(info.num_iters) < FitConfig().max_iters
    chex.assert_shape(info.cov, (3, 3))


def test_fit_covariance_matches_empirical_error_over_seeds():
    noise, num_seeds = 0.02, 48
    recs = [_record(jnp.tile(TRUTH, (25, 1)), seed, noise) for seed in range(num_seeds)]
    w = jnp.stack([r[0] for r in recs])
    x = jnp.stack([r[1] for r in recs])
    fit = jax.vmap(
        lambda w_u, x_u: fit_least_squares(_toy_measure, w_u, x_u, TRUTH * 0)
    )
    theta, info = fit(w, x)
    assert bool(jnp.all(info.converged))
    z = (theta - TRUTH) / info.theta_std  # [seeds, P], ~ N(0, 1) if cov is honest
    mean_sq = float(jnp.mean(z**2))
    assert 0.55 < mean_sq < 1.6, mean_sq
    # s^2 recovers the noise variance.
    s2 = 2 * info.cost / (25 * 4 - 3)
    assert 0.7 < float(jnp.mean(s2)) / noise**2 < 1.3


def test_fit_ignores_masked_padding():
    w, x = _record(jnp.tile(TRUTH, (20, 1)), seed=1, noise=0.01)
    w_pad = jnp.concatenate([w, jnp.zeros((5, 1))])
    x_pad = jnp.concatenate([x, jnp.full((5, 4), jnp.nan)])
    mask = jnp.arange(25) < 20
    meas = Measurement(centre=jnp.zeros(4), noise_std=jnp.array([1.0, 2.0, 0.5, 1.0]))
    theta, info = fit_least_squares(_toy_measure, w, x, jnp.zeros(3), measurement=meas)
    theta_pad, info_pad = fit_least_squares(
        _toy_measure, w_pad, x_pad, jnp.zeros(3), mask=mask, measurement=meas
    )
    np.testing.assert_allclose(theta_pad, theta, atol=1e-10)
    np.testing.assert_allclose(info_pad.cov, info.cov, rtol=1e-6)


def test_fit_rejects_steps_into_undefined_region():
    def sqrt_model(w_t, theta):
        return jnp.sqrt(theta) * w_t  # NaN for theta < 0: a failed "model evaluation"

    w = jnp.linspace(0.5, 2.0, 10)[:, None]
    x = 0.1 * w
    theta, info = fit_least_squares(sqrt_model, w, x, jnp.array([1.0]))
    assert bool(info.converged)
    np.testing.assert_allclose(theta, [0.01], atol=1e-9)


def test_sliding_window_tracks_a_step_change():
    theta_a, theta_b = TRUTH, TRUTH + jnp.array([-0.1, 0.05, 0.08])
    num_steps, t_change, window = 40, 20, 6
    theta_seq = jnp.where(jnp.arange(num_steps)[:, None] < t_change, theta_a, theta_b)
    w, x = _record(theta_seq, seed=2)
    meas = Measurement(centre=jnp.zeros(4), noise_std=jnp.ones(4))
    cfg = LeastSquaresConfig(window=window, num_iters=4)
    ls = make_least_squares(_toy_measure, cfg, meas, theta0=jnp.zeros(3))
    out = jax.jit(run_calibrator, static_argnums=0)(ls, w, x)
    chex.assert_tree_all_finite(out)
    np.testing.assert_allclose(
        out.theta[3:t_change], jnp.tile(theta_a, (17, 1)), atol=1e-7
    )
    np.testing.assert_allclose(
        out.theta[t_change + window :],
        jnp.tile(theta_b, (num_steps - 26, 1)),
        atol=1e-7,
    )
    # While the window straddles the change the estimate is in between, not at either.
    mid = out.theta[t_change + window // 2]
    assert float(jnp.linalg.norm(mid - theta_a)) > 1e-3
    assert float(jnp.linalg.norm(mid - theta_b)) > 1e-3
    # xhat is F(w_t, theta_t), read from the cached residual.
    np.testing.assert_allclose(
        out.xhat, jax.vmap(_toy_measure)(w, out.theta), atol=1e-10
    )


def test_tight_prior_holds_the_previous_estimate():
    w, x = _record(jnp.tile(TRUTH, (8, 1)), seed=3)
    meas = Measurement(centre=jnp.zeros(4), noise_std=jnp.ones(4))
    theta_scale = jnp.array([0.5, 1.0, 2.0])
    loose = make_least_squares(
        _toy_measure,
        LeastSquaresConfig(window=4, prior_std=10.0),
        meas,
        theta0=jnp.zeros(3),
        theta_scale=theta_scale,
    )
    tight = make_least_squares(
        _toy_measure,
        LeastSquaresConfig(window=4, prior_std=1e-6),
        meas,
        theta0=jnp.zeros(3),
        theta_scale=theta_scale,
    )
    out_loose, out_tight = run_calibrator(loose, w, x), run_calibrator(tight, w, x)
    np.testing.assert_allclose(out_loose.theta[-1], TRUTH, atol=1e-3)
    np.testing.assert_allclose(out_tight.theta, 0.0, atol=1e-3)
    assert bool(jnp.all(out_tight.aux["theta_std"] < out_loose.aux["theta_std"]))


def test_ls_step_eager_equals_jit():
    w, x = _record(jnp.tile(TRUTH, (2, 1)), seed=4)
    meas = Measurement(centre=jnp.zeros(4), noise_std=jnp.ones(4))
    ls = make_least_squares(
        _toy_measure, LeastSquaresConfig(window=3), meas, theta0=jnp.zeros(3)
    )
    state = ls.init(None, w[0], x[0])
    eager = ls.step(state, w[0], x[0])
    chex.assert_trees_all_close(eager, jax.jit(ls.step)(state, w[0], x[0]), atol=1e-12)


def test_ls_step_compiles_once():
    w, x = _record(jnp.tile(TRUTH, (3, 1)), seed=5)
    meas = Measurement(centre=jnp.zeros(4), noise_std=jnp.ones(4))
    ls = make_least_squares(
        _toy_measure, LeastSquaresConfig(window=2), meas, theta0=jnp.zeros(3)
    )
    chex.clear_trace_counter()
    step = jax.jit(chex.assert_max_traces(ls.step, n=1))
    state = ls.init(None, w[0], x[0])
    for t in range(3):
        state, out = step(state, w[t], x[t])
    assert int(state.pos) == 1  # ring buffer of 2 wrapped around
    chex.assert_tree_all_finite(out)


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="window"):
        LeastSquaresConfig(window=0)
    with pytest.raises(ValueError, match="prior_std"):
        LeastSquaresConfig(prior_std=-1.0)
    with pytest.raises(ValueError, match="max_iters"):
        FitConfig(max_iters=0)
    with pytest.raises(ValueError, match="theta0"):
        fit_least_squares(
            _toy_measure, jnp.zeros((5, 1)), jnp.zeros((5, 4)), jnp.zeros((3, 1))
        )
    with pytest.raises(ValueError, match="mask"):
        fit_least_squares(
            _toy_measure,
            jnp.zeros((5, 1)),
            jnp.zeros((5, 4)),
            jnp.zeros(3),
            mask=jnp.ones(4, bool),
        )
