"""The error a random-walk filter predicts for itself (std and lag bias) and the
relative band fitted on it."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.calibrators.uncertainty.conformal import (
    UNCERTAINTY_FILE,
    ThetaBand,
    band_coverage,
    band_std,
    fit_band,
    load_band,
    save_band,
)
from jaxcal.calibrators.uncertainty.lag_scale import (
    filter_error_scale,
    initial_trend,
    trend_rate,
    update_trend,
)


def test_lag_bias_is_the_steady_filters_p_over_q_squared():
    # a scalar Kalman filter with a random walk q tracking a noise-free ramp: its
    # steady error is -P r / q^2 (lag_scale's derivation), P its posterior variance
    q, noise, rate, cov, theta_hat = 0.01, 0.05, 2e-3, 1.0, 0.0
    for t in range(2000):
        pred = cov + q**2
        gain = pred / (pred + noise**2)
        theta_hat += gain * (rate * t - theta_hat)
        cov = (1 - gain) * pred
    err = theta_hat - rate * 1999
    scale = filter_error_scale(
        jnp.array([[cov]]), jnp.array([rate]), jnp.array([1.0]), q
    )
    assert err == pytest.approx(-cov * rate / q**2, rel=1e-6)
    assert float(scale[0]) == pytest.approx(np.hypot(np.sqrt(cov), err), rel=1e-5)


def test_trend_follows_a_line_from_its_first_sample():
    trend = initial_trend(2, jnp.float32)
    for t in range(200):
        theta = jnp.array([1.0 + 0.01 * t, -2.0], jnp.float32)
        trend = update_trend(trend, jnp.asarray(t > 0), theta)
    np.testing.assert_allclose(trend_rate(trend), [0.01, 0.0], atol=1e-5)


def test_relative_band_scales_with_the_predicted_error(tmp_path):
    # errors whose size is the scale of each unit (one in four drifts fast): a
    # relative band covers the fast ones too, a pooled one about 0.6 of them
    rng = np.random.default_rng(0)
    scale = np.where(np.arange(40) % 4, 1.0, 4.0)[:, None, None] * np.ones((40, 50, 1))
    theta = np.zeros((40, 50, 1))
    mask = np.ones((40, 50), bool)
    band = fit_band(rng.normal(size=scale.shape) * scale, theta, mask, scale=scale)
    pooled = fit_band(rng.normal(size=scale.shape) * scale, theta, mask)
    assert band.relative and not pooled.relative
    fresh = rng.normal(size=scale.shape) * scale
    fast = mask & (np.arange(40) % 4 == 0)[:, None]
    assert band_coverage(band, fresh, theta, fast, scale=scale)[0] > 0.85
    assert band_coverage(pooled, fresh, theta, fast)[0] < 0.7
    np.testing.assert_allclose(
        band_std(band, 0, jnp.array([2.0])), 2 * band.std[0], rtol=1e-6
    )
    with pytest.raises(ValueError, match="error scale"):
        band_std(band, 3)
    save_band(tmp_path / UNCERTAINTY_FILE, band, {"level": 0.9})
    assert load_band(tmp_path).relative
    save_band(tmp_path / UNCERTAINTY_FILE, pooled, {"level": 0.9})
    assert "relative" not in (tmp_path / UNCERTAINTY_FILE).read_text()
    assert not load_band(tmp_path).relative
    assert not ThetaBand(edges=band.edges, std=band.std).relative
