"""The split-conformal theta band: coverage on fresh draws, bucket merging, the
jitted lookup and the file round trip."""

import jax
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
    log_edges,
    merge_small_buckets,
    save_band,
    z_value,
)


def _draws(rng, units, length, scale):
    """Errors whose std decays from 10x at t = 0 to 1x (a start-up transient)."""
    t = np.arange(length)
    sigma = scale * np.array([1.0, 3.0]) * (1 + 9 * np.exp(-t / 4))[:, None]
    theta = rng.normal(size=(units, length, 2))
    theta_hat = theta + rng.normal(size=(units, length, 2)) * sigma
    mask = np.ones((units, length), bool)
    mask[0, length // 2 :] = False  # one shorter unit: padding is not scored
    return theta_hat, theta, mask


def test_band_covers_ninety_percent_of_fresh_draws():
    rng = np.random.default_rng(0)
    band = fit_band(*_draws(rng, 20, 100, 1e-3))
    # log-spaced buckets, the early ones wider (the transient)
    assert int(band.edges[0]) == 0 and band.std.shape == (len(band.edges), 2)
    assert float(band.std[0, 0]) > 3 * float(band.std[-1, 0])
    assert float(band.std[-1, 1]) == pytest.approx(3 * float(band.std[-1, 0]), 0.2)
    pooled, per = band_coverage(band, *_draws(rng, 200, 100, 1e-3))
    assert 0.88 <= pooled <= 0.93 and np.all((per > 0.87) & (per < 0.94))
    # a band fitted without the transient's own buckets misses early samples
    flat = fit_band(*_draws(rng, 20, 100, 1e-3), edges=[0])
    theta_hat, theta, mask = _draws(rng, 200, 100, 1e-3)
    early = mask.copy()
    early[:, 8:] = False
    assert band_coverage(flat, theta_hat, theta, early)[0] < 0.6
    assert band_coverage(band, theta_hat, theta, early)[0] > 0.85


def test_conformal_quantile_is_the_finite_sample_rank():
    # n = 20 scores 1..20: rank ceil(21 * 0.9) = 19
    err = np.arange(1.0, 21.0)[None, :, None]
    band = fit_band(err, np.zeros_like(err), np.ones((1, 20), bool), edges=[0])
    assert float(band.std[0, 0]) == pytest.approx(19 / z_value(0.9), rel=1e-6)
    assert z_value(0.9) == pytest.approx(1.6449, abs=1e-4)


def test_small_buckets_merge_into_a_neighbour():
    edges = np.array([0, 1, 2, 4, 8, 16, 32, 64])
    counts = np.array([1, 1, 2, 4, 8, 16, 32, 10])
    # 1+1+2+4+8+16 = 32 samples before 32; the short last bucket joins the previous
    assert merge_small_buckets(edges, counts, 20).tolist() == [0, 32]
    assert merge_small_buckets(edges, counts, 1).tolist() == edges.tolist()
    assert merge_small_buckets(edges, counts, 1000).tolist() == [0]
    # one unit of 40 samples: [0, 32) holds 32, [32, 40) only 8 -> one bucket
    err = np.ones((1, 40, 1))
    band = fit_band(err, 0 * err, np.ones((1, 40), bool))
    assert band.edges.tolist() == [0]
    assert log_edges(9).tolist() == [0, 1, 2, 4, 8]


def test_fit_band_rejects_bad_input():
    ok = np.zeros((2, 30, 1))
    with pytest.raises(ValueError, match=r"\[U, T, P\]"):
        fit_band(ok, ok[..., 0], np.ones((2, 30), bool))
    with pytest.raises(ValueError, match="mask"):
        fit_band(ok, ok, np.ones((2, 29), bool))
    with pytest.raises(ValueError, match="at least 20"):
        fit_band(ok, ok, np.zeros((2, 30), bool))
    with pytest.raises(ValueError, match="edges"):
        fit_band(ok, ok, np.ones((2, 30), bool), edges=[1, 4])


@pytest.mark.parametrize("wrap", [lambda f: f, jax.jit])
def test_band_std_looks_up_the_bucket_under_jit(wrap):
    band = ThetaBand(
        edges=jnp.array([0, 2, 8], jnp.int32),
        std=jnp.array([[3.0, 30.0], [2.0, 20.0], [1.0, 10.0]]),
    )
    lookup = wrap(band_std)
    expected = {0: 3.0, 1: 3.0, 2: 2.0, 7: 2.0, 8: 1.0, 10_000: 1.0}
    for t, value in expected.items():
        out = lookup(band, jnp.int32(t))
        assert out.shape == (2,)
        np.testing.assert_allclose(out, [value, 10 * value])
    # inside a scan over time, as a deployed calibrator would call it
    stds = jax.jit(jax.vmap(band_std, in_axes=(None, 0)))(band, jnp.arange(10))
    assert stds.shape == (10, 2) and float(stds[9, 0]) == 1.0


def test_save_and_load_round_trip(tmp_path):
    assert load_band(tmp_path) is None
    band = ThetaBand(
        edges=jnp.array([0, 4, 16], jnp.int32),
        std=jnp.array([[3e-4], [2e-4], [1e-4]], jnp.float32),
    )
    save_band(tmp_path / UNCERTAINTY_FILE, band, {"level": 0.9, "num_samples": 7})
    loaded = load_band(tmp_path)
    assert loaded.edges.dtype == jnp.int32
    np.testing.assert_array_equal(loaded.edges, band.edges)
    np.testing.assert_allclose(loaded.std, band.std)
    (tmp_path / UNCERTAINTY_FILE).write_text('{"edges": [1], "std": [[1.0]]}')
    with pytest.raises(ValueError, match="uncertainty.json"):
        load_band(tmp_path)
