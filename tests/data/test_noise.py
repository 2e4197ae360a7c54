"""Sensor noise at a given SNR, output bias and output noise (pure JAX)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.data.noise import (
    add_output_noise,
    add_sensor_noise_snr,
    apply_output_bias,
    signal_power,
)


def clean_signal(num_rows=100_000):
    """Three sensors with very different scales and offsets (T30-, P2-, Wf-like)."""
    t = jnp.linspace(0.0, 20.0, num_rows)[:, None]
    return jnp.array([1400.0, 14.7, 2.0]) + jnp.array([50.0, 1.0, 0.5]) * jnp.sin(
        t * jnp.array([1.0, 0.3, 2.0])
    )


@pytest.mark.parametrize("transform", [lambda f: f, jax.jit])
@pytest.mark.parametrize("snr_db", [20.0, 70.0])
def test_empirical_snr_matches_request(transform, snr_db):
    x = clean_signal()
    noisy = transform(add_sensor_noise_snr)(jax.random.key(0), x, snr_db)
    noise_power = np.mean(np.square(noisy - x), axis=0)
    ratio = np.mean(np.square(x), axis=0) / noise_power
    # 100k samples: the noise-power estimate has ~0.5 % relative error.
    np.testing.assert_allclose(ratio, 10 ** (snr_db / 10), rtol=0.03)


def test_given_signal_power_sets_the_noise_level():
    x = clean_signal(50_000)
    power = jnp.array([4.0, 1.0, 0.25])
    noisy = add_sensor_noise_snr(jax.random.key(1), x, 0.0, signal_power=power)
    np.testing.assert_allclose(np.std(noisy - x, axis=0), [2.0, 1.0, 0.5], rtol=0.03)
    # Same key and same power -> identical noise for any chunk content (chunked runs).
    again = add_sensor_noise_snr(jax.random.key(1), 2 * x, 0.0, signal_power=power)
    np.testing.assert_allclose(again - 2 * x, noisy - x, atol=1e-9)


def test_signal_power_ignores_masked_rows():
    x = jnp.array([[[1.0, 2.0], [3.0, 4.0], [1e6, 1e6]]])  # [U=1, T=3, S=2]
    mask = jnp.array([[True, True, False]])
    np.testing.assert_allclose(signal_power(x, mask), [5.0, 10.0])


def test_output_bias_is_exact():
    x = clean_signal(10)
    np.testing.assert_array_equal(apply_output_bias(x, 1.02), x * 1.02)


def test_output_noise_has_sigma_in_normalised_units():
    x = clean_signal(100_000)
    mean, std = x.mean(axis=0), x.std(axis=0)
    noisy = jax.jit(add_output_noise)(jax.random.key(2), x, 0.1, mean, std)
    delta = (noisy - mean) / std - (x - mean) / std
    np.testing.assert_allclose(np.std(delta, axis=0), 0.1, rtol=0.03)
    np.testing.assert_allclose(np.mean(delta, axis=0), 0.0, atol=2e-3)


def test_traced_arguments_sweep_under_vmap():
    x = clean_signal(20_000)
    snrs = jnp.array([10.0, 30.0])
    noisy = jax.jit(jax.vmap(add_sensor_noise_snr, in_axes=(None, None, 0)))(
        jax.random.key(3), x, snrs
    )
    noise_power = np.mean(np.square(noisy - x), axis=1)[:, 0]
    ratio_db = 10 * np.log10(np.mean(np.square(x[:, 0])) / noise_power)
    np.testing.assert_allclose(ratio_db, snrs, atol=0.2)


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda x, k: add_sensor_noise_snr(k, x, float("inf")),
            "snr_db must be finite",
        ),
        (
            lambda x, k: add_sensor_noise_snr(k, x, float("nan")),
            "snr_db must be finite",
        ),
        (lambda x, k: apply_output_bias(x, 0.0), "alpha must be finite and > 0"),
        (lambda x, k: apply_output_bias(x, -1.02), "alpha must be finite and > 0"),
        (lambda x, k: add_output_noise(k, x, -0.1, 0.0, 1.0), "sigma must be"),
        (lambda x, k: add_output_noise(k, x, 0.1, 0.0, 0.0), "std must be"),
    ],
)
def test_bad_arguments_raise(call, match):
    with pytest.raises(ValueError, match=match):
        call(clean_signal(4), jax.random.key(0))
