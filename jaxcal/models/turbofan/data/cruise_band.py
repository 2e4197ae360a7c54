"""The paper's Dataset #2 trajectory: smooth random motion inside a cruise band.

:func:`sample_cruise_band` drifts (alt, Mach, TRA) as a smooth random walk reflected
inside a narrow cruise band (alt 25.7-29 kft, Mach 0.67-0.74, TRA 69-82 %); a pure
function of a PRNG key with static shapes, like the N-CMAPSS-like flights of
:mod:`jaxcal.models.turbofan.data.flights`.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from jaxcal.models.turbofan.data.flight_signals import FlightProfile, smooth_noise
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.typedefs import Array, PRNGKey

Range = tuple[float, float]


@dataclasses.dataclass(frozen=True)
class CruiseBand:
    """Narrow cruise band of the paper's Dataset #2 (Table 1: AGTF30 column)."""

    alt_ft: Range = (25_700.0, 29_000.0)
    mach: Range = (0.67, 0.74)
    tra: Range = (69.1, 82.4)
    dt_s: float = 1.0
    traverse_s: float = 1500.0  # typical time to drift across the band once
    velocity_tau_s: float = 120.0  # correlation time of the random velocity
    jitter_frac: float = 0.01  # white noise std as a fraction of the band width
    delta_t_day_r: float = 5.0  # small off-standard day [degR]
    delta_t_drift_r: float = 1.0

    def __post_init__(self):
        for name in ("alt_ft", "mach", "tra"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ValueError(f"CruiseBand.{name} must be (lo, hi) with lo < hi")


def _reflect(x: Array, lo: Array, hi: Array) -> Array:
    """Fold x into [lo, hi] as a path reflected at both edges (triangle wave)."""
    width = hi - lo
    y = jnp.mod(x - lo, 2.0 * width)
    return lo + jnp.where(y > width, 2.0 * width - y, y)


def sample_cruise_band(
    key: PRNGKey, num_steps: int, band: CruiseBand = CruiseBand()
) -> FlightProfile:
    """Smooth random motion of (alt, Mach, TRA) reflected inside a cruise band.

    Each channel integrates a smooth random velocity (unit-variance :func:`smooth_noise`
    scaled so that a displacement of one band width takes about ``band.traverse_s``: for
    an integrated correlated velocity, std(displacement) ~ sigma_v sqrt(2 tau t)), adds
    white jitter and is folded back into the band. T2 comes from ISA plus a small dT.

    Args:
        key: PRNG key.
        num_steps: T (static); the paper uses 5,000 samples at 1 Hz.
        band: static :class:`CruiseBand`.

    Returns:
        :class:`FlightProfile` with every sample valid.
    """
    key_start, key_motion, key_jitter, key_day, key_drift = jax.random.split(key, 5)
    lo = jnp.asarray([band.alt_ft[0], band.mach[0], band.tra[0]])
    hi = jnp.asarray([band.alt_ft[1], band.mach[1], band.tra[1]])
    width = hi - lo
    start = lo + width * jax.random.uniform(key_start, (3,))
    velocity = smooth_noise(key_motion, num_steps, 3, band.dt_s, band.velocity_tau_s)
    sigma_v = width / math.sqrt(2.0 * band.velocity_tau_s * band.traverse_s)
    path = start + jnp.cumsum(velocity * sigma_v * band.dt_s, axis=0)
    path = path + band.jitter_frac * width * jax.random.normal(
        key_jitter, (num_steps, 3)
    )
    x = _reflect(path, lo, hi)
    day = jax.random.uniform(
        key_day, (), minval=-band.delta_t_day_r, maxval=band.delta_t_day_r
    )
    drift = smooth_noise(key_drift, num_steps, 1, band.dt_s, 1800.0)[:, 0]
    t2 = isa_total_temperature(x[:, 0], x[:, 1], day + band.delta_t_drift_r * drift)
    duration = jnp.asarray(num_steps * band.dt_s, dtype=x.dtype)
    return FlightProfile(
        w=jnp.concatenate([x, t2[:, None]], axis=-1),
        mask=jnp.ones((num_steps,), dtype=bool),
        duration_s=duration,
        flight_time_s=duration,
    )
