"""Measurement-noise and model-inadequacy variants of a data set (pure JAX).

The paper's robustness tables perturb either the measurements or the model output:
sensor noise at a given signal-to-noise ratio (70 dB), a multiplicative output bias (F x
1.02) and additive output noise in normalised units (F + N(0, 0.1)). Each is a pure
function with an explicit PRNG key, jittable and vmappable; the scalar arguments may be
traced (for sweeps), in which case their range checks are skipped because a traced value
has no concrete value to check.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.typedefs import Array, PRNGKey


def _concrete(value) -> np.ndarray | None:
    """``value`` as numpy, or ``None`` when it is traced and cannot be checked."""
    if isinstance(value, jax.core.Tracer):
        return None
    return np.asarray(value)


def _check(name: str, value, ok, expected: str) -> None:
    concrete = _concrete(value)
    if concrete is not None and not np.all(ok(concrete)):
        raise ValueError(f"{name} must be {expected}, got {value}")


def signal_power(x: Array, mask: Array | None = None) -> Array:
    """Mean power ``mean(x**2)`` per sensor over all leading axes (valid rows only).

    Args:
        x: ``[..., S]`` sensor values in physical units.
        mask: optional ``[...]`` bool, True on valid rows (e.g. ``Padded.mask``).

    Returns:
        ``[S]`` signal power.
    """
    squared = jnp.square(x).reshape(-1, x.shape[-1])
    if mask is None:
        return squared.mean(axis=0)
    weight = jnp.broadcast_to(mask, x.shape[:-1]).reshape(-1, 1).astype(x.dtype)
    return (squared * weight).sum(axis=0) / jnp.maximum(weight.sum(), 1.0)


def add_sensor_noise_snr(
    key: PRNGKey, x: Array, snr_db, *, signal_power: Array | None = None
) -> Array:
    """Add white Gaussian noise at a given signal-to-noise ratio (AWGN definition).

    ``SNR_dB = 10 log10(P_signal / P_noise)`` per sensor with ``P_signal = mean(x**2)``,
    so the noise std of sensor ``s`` is ``sqrt(P_signal[s] / 10**(SNR_dB / 10))``.

    ``P_signal`` is estimated from ``x`` itself unless given. When a data set is
    generated in chunks, pass the power of the whole data set (or of a fixed reference,
    see :func:`signal_power`): otherwise every chunk gets its own noise level and the
    result depends on the chunking.

    Args:
        key: PRNG key.
        x: ``[..., S]`` clean sensor values in physical units.
        snr_db: SNR in dB (scalar, or ``[S]`` per sensor), finite.
        signal_power: optional ``[S]`` signal power to use instead of ``mean(x**2)``.

    Returns:
        ``[..., S]`` noisy sensor values.
    """
    _check("snr_db", snr_db, np.isfinite, "finite (dB)")
    if signal_power is None:
        power = jnp.mean(jnp.square(x).reshape(-1, x.shape[-1]), axis=0)
    else:
        _check("signal_power", signal_power, lambda p: p >= 0, ">= 0 per sensor")
        power = jnp.asarray(signal_power, dtype=x.dtype)
    noise_std = jnp.sqrt(power / 10.0 ** (jnp.asarray(snr_db, x.dtype) / 10.0))
    return x + noise_std * jax.random.normal(key, x.shape, dtype=x.dtype)


def apply_output_bias(x: Array, alpha) -> Array:
    """Multiplicative model-output bias ``x * alpha`` (the paper's F x 1.02).

    Args:
        x: ``[..., S]`` model outputs.
        alpha: scalar or ``[S]`` factor, > 0.

    Returns:
        ``[..., S]`` biased outputs.
    """
    _check("alpha", alpha, lambda a: np.isfinite(a) & (a > 0), "finite and > 0")
    return x * alpha


def add_output_noise(key: PRNGKey, x: Array, sigma, mean: Array, std: Array) -> Array:
    """Additive model-output noise in normalised units (the paper's F + N(0, 0.1)).

    ``x_n = (x - mean) / std``; ``x_n + sigma * eps``, ``eps ~ N(0, 1)``; mapped back
    with ``x_n * std + mean``, i.e. ``x + sigma * std * eps``.

    Args:
        key: PRNG key.
        x: ``[..., S]`` model outputs in physical units.
        sigma: noise std in normalised units (scalar or ``[S]``), >= 0.
        mean: ``[S]`` normalisation mean (e.g. ``NormStats.x_mean``).
        std: ``[S]`` normalisation std, > 0.

    Returns:
        ``[..., S]`` noisy outputs in physical units.
    """
    _check("sigma", sigma, lambda s: np.isfinite(s) & (s >= 0), "finite and >= 0")
    _check("std", std, lambda s: np.isfinite(s) & (s > 0), "finite and > 0")
    x_norm = (x - mean) / std
    x_norm = x_norm + sigma * jax.random.normal(key, x.shape, dtype=x.dtype)
    return x_norm * std + mean
