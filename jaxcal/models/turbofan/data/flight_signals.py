"""What both flight generators share: the padded flight record and smooth noise.

:class:`FlightProfile` is the output of
:func:`jaxcal.models.turbofan.data.flights.sample_flight` and
:func:`jaxcal.models.turbofan.data.cruise_band.sample_cruise_band`. Their noise is
second-order low-pass filtered Gaussian noise (two first-order filters run by
``lax.scan``, :func:`smooth_noise`): smooth, like recorded flight data.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
from jax import lax

from jaxcal.typedefs import Array, PRNGKey


class FlightProfile(NamedTuple):
    """One flight, padded. Padded samples repeat the last recorded condition."""

    w: Array  # [T, 4] alt [ft], Mach, TRA [%], T2 [degR] (CONDITION_NAMES)
    mask: Array  # [T] bool, True where recorded
    duration_s: Array  # [] recorded time above the floor [s]
    flight_time_s: Array  # [] total flight time incl. the part below the floor [s]


def _linear_recurrence(a: float, u: Array, z_init: Array) -> Array:
    """z_t = a z_{t-1} + u_t along axis 0 with z_{-1} = z_init.

    A sequential ``lax.scan``: its body compiles once whatever T is, whereas a parallel
    ``associative_scan`` over 25,200 samples took seconds to compile on CPU.
    """

    def step(z, u_t):
        z = a * z + u_t
        return z, z

    _, z = lax.scan(step, z_init, u)
    return z


def smooth_noise(key: PRNGKey, num_steps: int, num_channels: int, dt_s, tau_s) -> Array:
    """Stationary unit-variance noise through two cascaded first-order low-pass filters.

    x_t = a x_{t-1} + e_t, y_t = a y_{t-1} + x_t with a = exp(-dt/tau); (x, y) start
    from their stationary joint law, so there is no transient; y is scaled to unit
    variance.

    Args:
        key: PRNG key.
        num_steps: T (static).
        num_channels: C (static), independent channels.
        dt_s: sampling period [s] (static float).
        tau_s: filter time constant [s] (static float).

    Returns:
        [T, C] noise.
    """
    a = math.exp(-dt_s / tau_s)
    var_x = 1.0 / (1.0 - a * a)
    cov_xy = var_x / (1.0 - a * a)
    var_y = (2.0 * a * a * cov_xy + var_x) / (1.0 - a * a)
    key_init, key_drive = jax.random.split(key)
    z0 = jax.random.normal(key_init, (2, num_channels))
    x_init = math.sqrt(var_x) * z0[0]
    y_init = (
        cov_xy / math.sqrt(var_x) * z0[0]
        + math.sqrt(max(var_y - cov_xy**2 / var_x, 0.0)) * z0[1]
    )
    drive = jax.random.normal(key_drive, (num_steps, num_channels))
    x = _linear_recurrence(a, drive, x_init)
    return _linear_recurrence(a, x, y_init) / math.sqrt(var_y)
