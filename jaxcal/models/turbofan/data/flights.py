"""Jittable generators of operating conditions w = (alt, Mach, TRA, T2).

Two generators, both pure functions of a PRNG key with static output shapes, so they can
be vmapped over keys (one flight per key) and jitted at the data-set builder:

* :func:`sample_flight`: one N-CMAPSS-like flight (climb, cruise, descent) of flight
  class 1 / 2 / 3 (1-3 h, 3-5 h, 5-7 h total flight time), recorded only above 10,000 ft
  as in N-CMAPSS DS02, and padded to ``FlightConfig.num_steps`` samples with a validity
  mask.
* :func:`sample_cruise_band` (:mod:`.cruise_band`, re-exported here): the paper's
  Dataset #2 trajectory, a smooth random walk reflected inside a narrow cruise band
  (alt 25.7-29 kft, Mach 0.67-0.74, TRA 69-82 %).

Noise is second-order low-pass filtered Gaussian noise (two first-order filters run by
``lax.scan``, :mod:`.flight_signals`), plus a little white jitter: smooth but noisy,
like recorded flight data. T2 = (T_ISA(alt) + dT)(1 + 0.2 M^2) with an off-standard-day
dT within +-25 degR (data_facts.md section 4; physics_facts.md 2.1).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.models.turbofan.data.cruise_band import (  # noqa: F401 (re-exported: the other generator)
    CruiseBand,
    sample_cruise_band,
)
from jaxcal.models.turbofan.data.flight_signals import FlightProfile, smooth_noise
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.typedefs import Array, PRNGKey

Range = tuple[float, float]


@dataclasses.dataclass(frozen=True)
class FlightConfig:
    """Static flight-profile settings (hashable: pass it by closure or as a static arg).

    Ranges are (low, high) of a uniform draw. "short" / "long" ranges are interpolated
    by total flight time, so shorter flights cruise lower and slower.
    """

    dt_s: float = 1.0  # sampling period [s]; N-CMAPSS is 1 Hz, larger values subsample
    min_alt_ft: float = 10_000.0  # recording floor (N-CMAPSS DS02 records alt > 10 kft)
    max_alt_ft: float = 35_000.0  # ceiling (paper Table 1: 35.0k; DS02 max 35,033 ft)
    class_hours: tuple[Range, ...] = ((1.0, 3.0), (3.0, 5.0), (5.0, 7.0))  # Fc 1, 2, 3
    below_floor_s: Range = (900.0, 1500.0)  # taxi + climb to / descent from 10 kft
    cruise_alt_short_ft: Range = (20_000.0, 28_000.0)  # cruise level of 1 h flights
    cruise_alt_long_ft: Range = (31_000.0, 35_000.0)  # cruise level of 7 h flights
    cruise_mach_short: Range = (0.62, 0.70)
    cruise_mach_long: Range = (0.70, 0.735)  # paper Table 1: Mach <= 0.75
    climb_start_mach: Range = (0.38, 0.48)  # ~250 KIAS at 10 kft
    descent_end_mach: Range = (0.27, 0.40)  # paper Table 1: Mach >= 0.26
    climb_rate_fpm: Range = (1500.0, 2500.0)  # mean rate over the recorded climb
    descent_rate_fpm: Range = (1500.0, 2500.0)
    climb_shape: float = 1.6  # alt = 1 - (1 - s)^p: rate falls as the aircraft climbs
    descent_shape: float = 1.4  # alt = 1 - s^q: gentle top of descent
    climb_start_tra: Range = (78.0, 85.0)  # climb thrust, decreasing schedule ...
    climb_end_tra: Range = (72.0, 80.0)  # ... towards the top of climb
    cruise_tra: Range = (60.0, 78.0)
    descent_tra: Range = (27.0, 36.0)  # near idle (paper Table 1: TRA >= 23.6)
    num_alt_steps: int = 2  # candidate step climbs during cruise
    alt_step_choices_ft: tuple[float, ...] = (-1000.0, 0.0, 1000.0, 2000.0)
    alt_step_ramp_s: float = 90.0  # duration of one step climb
    step_tra_boost: float = 4.0  # extra TRA [%] per 1000 ft of step climb
    phase_blend_s: float = 60.0  # TRA transition time between phases
    noise_tau_s: float = 60.0  # correlation time of the smooth noise
    alt_noise_ft: float = 60.0  # std of smooth altitude noise
    mach_noise: float = 0.003
    tra_noise: float = 1.2
    alt_jitter_ft: float = 10.0  # std of white noise (recording noise)
    mach_jitter: float = 0.0005
    tra_jitter: float = 0.2
    mach_limits: Range = (0.2, 0.75)
    tra_limits: Range = (20.0, 100.0)
    delta_t_day_r: float = 20.0  # |constant off-standard dT| bound [degR]
    delta_t_drift_r: float = 2.0  # std of the slow dT drift within a flight [degR]
    delta_t_drift_tau_s: float = 1800.0
    delta_t_limit_r: float = 25.0  # hard bound on |dT| (data_facts.md section 4)

    def __post_init__(self):
        if self.dt_s <= 0:
            raise ValueError(f"FlightConfig.dt_s must be > 0 seconds, got {self.dt_s}")
        if not self.class_hours or any(
            lo <= 0 or hi < lo for lo, hi in self.class_hours
        ):
            raise ValueError(
                "FlightConfig.class_hours must be ((lo, hi), ...) with 0 < lo <= hi, "
                f"got {self.class_hours}"
            )
        if not self.min_alt_ft < self.max_alt_ft:
            raise ValueError("FlightConfig needs min_alt_ft < max_alt_ft")

    @property
    def num_classes(self) -> int:
        return len(self.class_hours)

    @property
    def num_steps(self) -> int:
        """Static padded length T_max = ceil(longest flight time / dt_s)."""
        longest_s = 3600.0 * max(hi for _, hi in self.class_hours)
        return int(math.ceil(longest_s / self.dt_s))


def _lerp(bounds, u):
    lo, hi = bounds
    return lo + (hi - lo) * u


def _smoothstep(x):
    s = jnp.clip(x, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def _check_class(flight_class, num_classes: int) -> Array:
    if (
        isinstance(flight_class, numbers.Integral)
        and not 1 <= flight_class <= num_classes
    ):
        raise ValueError(
            f"flight_class must be in 1..{num_classes}, got {flight_class}"
        )
    return jnp.clip(jnp.asarray(flight_class, jnp.int32) - 1, 0, num_classes - 1)


class _Plan(NamedTuple):
    """The scalar draws of one flight: its length and the levels of its phases."""

    draws: Array  # [13] uniform draws; the last sets the descent rate (_cruise_timing)
    flight_time: Array  # [s], including the part below the floor
    recorded: Array  # [s] above the floor
    alt_cruise: Array  # initial cruise level [ft]
    mach_cruise: Array
    mach_start: Array  # at the floor in the climb
    mach_end: Array  # at the floor in the descent
    tra_c0: Array  # climb schedule start / end [%]
    tra_c1: Array
    tra_cruise: Array
    tra_desc: Array
    delta_t_day: Array  # off-standard day [degR]
    t_climb: Array  # recorded climb time [s]


class _Timing(NamedTuple):
    """When the phases and the step climbs happen."""

    step_size: Array  # [K] step climbs [ft] (0 when the cruise is too short)
    step_time: Array  # [K] their starts [s]
    t_descent: Array  # [s]
    t_tod: Array  # top of descent [s]
    level_end: Array  # cruise level after every step [ft]


def _top_alt(cfg: FlightConfig) -> float:
    """Highest nominal level: noise must not push the recorded altitude past the
    ceiling."""
    return cfg.max_alt_ft - 3.0 * cfg.alt_noise_ft


def _flight_plan(key: PRNGKey, idx: Array, cfg: FlightConfig) -> _Plan:
    """Draw the flight time of class ``idx`` and the phase levels; longer flights
    cruise higher and faster (levels interpolated by flight time)."""
    u = jax.random.uniform(key, (13,))
    hours = jnp.asarray(cfg.class_hours)[idx]
    flight_time = 3600.0 * _lerp(hours, u[0])
    longest = max(hi for _, hi in cfg.class_hours)
    shortest = min(lo for lo, _ in cfg.class_hours)
    frac = jnp.clip((flight_time / 3600.0 - shortest) / (longest - shortest), 0.0, 1.0)
    recorded = flight_time - _lerp(cfg.below_floor_s, u[1])

    floor, top = cfg.min_alt_ft, _top_alt(cfg)
    alt_lo = _lerp((cfg.cruise_alt_short_ft[0], cfg.cruise_alt_long_ft[0]), frac)
    alt_hi = _lerp((cfg.cruise_alt_short_ft[1], cfg.cruise_alt_long_ft[1]), frac)
    alt_cruise = jnp.clip(_lerp((alt_lo, alt_hi), u[2]), floor + 2000.0, top)
    mach_lo = _lerp((cfg.cruise_mach_short[0], cfg.cruise_mach_long[0]), frac)
    mach_hi = _lerp((cfg.cruise_mach_short[1], cfg.cruise_mach_long[1]), frac)
    mach_cruise = _lerp((mach_lo, mach_hi), u[3])
    mach_start, mach_end = (
        _lerp(cfg.climb_start_mach, u[4]),
        _lerp(cfg.descent_end_mach, u[5]),
    )
    tra_c0, tra_c1 = _lerp(cfg.climb_start_tra, u[6]), _lerp(cfg.climb_end_tra, u[7])
    tra_cruise, tra_desc = _lerp(cfg.cruise_tra, u[8]), _lerp(cfg.descent_tra, u[9])
    delta_t_day = _lerp((-cfg.delta_t_day_r, cfg.delta_t_day_r), u[10])

    t_climb = jnp.maximum(
        (alt_cruise - floor) / _lerp(cfg.climb_rate_fpm, u[11]) * 60.0, cfg.dt_s
    )
    return _Plan(
        u, flight_time, recorded, alt_cruise, mach_cruise, mach_start, mach_end,
        tra_c0, tra_c1, tra_cruise, tra_desc, delta_t_day, t_climb,
    )  # fmt: skip


def _cruise_level(alt_cruise: Array, ramp: Array, sizes: Array, cfg: FlightConfig):
    """The cruise level after the step climbs ``sizes`` [K] ramped ``ramp`` [..., K]
    (0: not started, 1: done), kept 2000 ft above the floor and below the top."""
    steps = jnp.sum(sizes * _smoothstep(ramp), axis=-1)
    return jnp.clip(alt_cruise + steps, cfg.min_alt_ft + 2000.0, _top_alt(cfg))


def _cruise_timing(key: PRNGKey, plan: _Plan, cfg: FlightConfig) -> _Timing:
    """Draw the step climbs and fit climb, cruise and descent into the recorded time."""
    floor = cfg.min_alt_ft
    key_step_t, key_step_size = jax.random.split(key)
    step_size = jax.random.choice(
        key_step_size, jnp.asarray(cfg.alt_step_choices_ft), (cfg.num_alt_steps,)
    )
    # The end level does not depend on when the steps happen, so the descent length (and
    # with it the cruise length) is known before the steps are placed inside the cruise.
    ones = jnp.ones((cfg.num_alt_steps,))
    descent_rate = _lerp(cfg.descent_rate_fpm, plan.draws[12]) / 60.0  # ft/s
    t_descent = (_cruise_level(plan.alt_cruise, ones, step_size, cfg) - floor) / (
        descent_rate
    )
    # Clamp at 0 so that odd configs shorten the flight rather than break it; a cruise
    # too short for one step climb gets none.
    t_cruise = jnp.maximum(plan.recorded - plan.t_climb - t_descent, 0.0)
    step_size = jnp.where(t_cruise > cfg.alt_step_ramp_s, step_size, 0.0)
    level_end = _cruise_level(plan.alt_cruise, ones, step_size, cfg)
    t_tod = plan.t_climb + t_cruise
    step_time = plan.t_climb + jax.random.uniform(key_step_t, (cfg.num_alt_steps,)) * (
        jnp.maximum(t_cruise - cfg.alt_step_ramp_s, 0.0)
    )
    return _Timing(step_size, step_time, t_descent, t_tod, level_end)


def _nominal_profile(t: Array, plan: _Plan, timing: _Timing, cfg: FlightConfig):
    """Noise-free (alt, Mach, TRA) [T] at times ``t``: a concave climb, the cruise
    with its step climbs, the descent; TRA blended between phases."""
    floor = cfg.min_alt_ft
    step_size, t_climb, t_tod = timing.step_size, plan.t_climb, timing.t_tod
    ramp = jnp.clip((t[:, None] - timing.step_time) / cfg.alt_step_ramp_s, 0.0, 1.0)
    s_climb = jnp.clip(t / t_climb, 0.0, 1.0)
    s_desc = jnp.clip((t - t_tod) / timing.t_descent, 0.0, 1.0)
    alt_cruise, level_end = plan.alt_cruise, timing.level_end
    alt_nom = jnp.where(
        t < t_climb,
        floor + (alt_cruise - floor) * (1.0 - (1.0 - s_climb) ** cfg.climb_shape),
        jnp.where(
            t < t_tod,
            _cruise_level(alt_cruise, ramp, step_size, cfg),
            level_end - (level_end - floor) * s_desc**cfg.descent_shape,
        ),
    )
    mach_start, mach_cruise = plan.mach_start, plan.mach_cruise
    mach_nom = jnp.where(
        t < t_climb,
        mach_start + (mach_cruise - mach_start) * (1.0 - (1.0 - s_climb) ** 2),
        mach_cruise + (plan.mach_end - mach_cruise) * s_desc**2,
    )
    w_cruise = _smoothstep((t - t_climb) / cfg.phase_blend_s)
    w_desc = _smoothstep((t - t_tod) / cfg.phase_blend_s)
    tra_climb = plan.tra_c0 + (plan.tra_c1 - plan.tra_c0) * s_climb
    bump = jnp.sum(step_size / 1000.0 * 4.0 * ramp * (1.0 - ramp), axis=-1)
    tra_nom = (
        (tra_climb * (1.0 - w_cruise) + plan.tra_cruise * w_cruise) * (1.0 - w_desc)
        + plan.tra_desc * w_desc
        + cfg.step_tra_boost * bump
    )
    return alt_nom, mach_nom, tra_nom


def _noisy_conditions(keys, nominal, delta_t_day: Array, cfg: FlightConfig) -> Array:
    """w [T, 4]: smooth noise and white jitter on the nominal (alt, Mach, TRA), each
    kept in its limits, and T2 of the ISA day offset by a drifting dT.

    Args:
        keys: (noise, jitter, dT drift) PRNG keys.
        nominal: (alt, Mach, TRA) [T] from :func:`_nominal_profile`.
    """
    key_noise, key_jitter, key_drift = keys
    alt_nom, mach_nom, tra_nom = nominal
    floor = cfg.min_alt_ft
    n = smooth_noise(key_noise, cfg.num_steps, 3, cfg.dt_s, cfg.noise_tau_s)
    j = jax.random.normal(key_jitter, (cfg.num_steps, 3))
    # Altitude noise fades out within 2000 ft of the floor: recorded samples stay above.
    fade = jnp.clip((alt_nom - floor) / 2000.0, 0.0, 1.0)
    alt = alt_nom + fade * (cfg.alt_noise_ft * n[:, 0] + cfg.alt_jitter_ft * j[:, 0])
    alt = jnp.clip(alt, floor, cfg.max_alt_ft)
    mach = jnp.clip(
        mach_nom + cfg.mach_noise * n[:, 1] + cfg.mach_jitter * j[:, 1],
        *cfg.mach_limits,
    )
    tra = jnp.clip(
        tra_nom + cfg.tra_noise * n[:, 2] + cfg.tra_jitter * j[:, 2], *cfg.tra_limits
    )
    drift = smooth_noise(key_drift, cfg.num_steps, 1, cfg.dt_s, cfg.delta_t_drift_tau_s)
    delta_t = jnp.clip(
        delta_t_day + cfg.delta_t_drift_r * drift[:, 0],
        -cfg.delta_t_limit_r,
        cfg.delta_t_limit_r,
    )
    return jnp.stack(
        [alt, mach, tra, isa_total_temperature(alt, mach, delta_t)], axis=-1
    )


def sample_flight(key: PRNGKey, flight_class, cfg: FlightConfig) -> FlightProfile:
    """Sample one climb / cruise / descent flight recorded above ``cfg.min_alt_ft``.

    The recorded part starts mid-climb at the floor: a concave climb (rate falling with
    altitude, TRA on a decreasing climb schedule, Mach accelerating to cruise Mach), a
    cruise at a level that grows with flight time, with up to ``num_alt_steps`` smooth
    step climbs (plus a TRA bump) and smooth Mach / TRA noise, then a descent at
    near-idle TRA back to the floor. TRA changes between phases are blended over
    ``phase_blend_s``.

    Args:
        key: PRNG key; the same key gives the same flight.
        flight_class: 1, 2 or 3 (Python int or traced int32 scalar, e.g. under vmap).
        cfg: static :class:`FlightConfig`.

    Returns:
        :class:`FlightProfile` with ``w`` [T_max, 4], ``mask`` [T_max].
    """
    idx = _check_class(flight_class, cfg.num_classes)
    key_plan, key_steps, key_noise, key_jitter, key_drift = jax.random.split(key, 5)
    plan = _flight_plan(key_plan, idx, cfg)
    timing = _cruise_timing(key_steps, plan, cfg)
    t = jnp.arange(cfg.num_steps) * cfg.dt_s
    nominal = _nominal_profile(t, plan, timing, cfg)
    w = _noisy_conditions(
        (key_noise, key_jitter, key_drift), nominal, plan.delta_t_day, cfg
    )
    duration = jnp.minimum(timing.t_tod + timing.t_descent, cfg.num_steps * cfg.dt_s)
    mask = t < duration
    last = jnp.maximum(jnp.sum(mask) - 1, 0)
    w = w[jnp.minimum(jnp.arange(cfg.num_steps), last)]
    return FlightProfile(
        w=w, mask=mask, duration_s=duration, flight_time_s=plan.flight_time
    )
