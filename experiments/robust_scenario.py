"""Randomised fleets of three models for the robust study (loop_robust.py).

The diagnosis is built on assumptions that the project's own generators share: one
operating pattern, smooth wear, white noise at a known level, every unit carrying the
effect. Here each record draws what the diagnosis does *not* assume (:func:`draw`):

* the number of units (2-5) and each unit's life; the operating conditions (the
  turbofan: one of three flight-profile families and each unit's flight class, 1-3
  samples per flight, every cycle or every other one; the heat exchanger: operating
  points wandering slowly within the rated range; the thermal model: a heater
  switched between random levels, a slowly wandering ambient);
* the shape of the declared parameter's wear per unit (linear, exponential,
  piecewise-linear with a knee; :func:`wear_shape`) and its end value, and the shape
  of an undeclared parameter's change per unit;
* the noise level (0.5x-2x the reference, log-uniform, a 0.8x-1.25x jitter per output)
  and colour: AR(1) along each unit's rows, coefficient 0 (one record in three) or
  0.3-0.8, the marginal std kept;
* which units carry the effect (1 to all, a random subset) and, for a step, its onset
  in each carrier (30-70 % of its life).

:func:`make_record` puts one effect of a kind (:mod:`jaxcal.diagnosis.kinds.table`) and
physical size on the carriers through the extended model
(:func:`jaxcal.diagnosis.kinds.signatures.signatures`; a model with memory is simulated
with the effect in it) and adds the noise.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.diagnosis.data.prepare import DEFAULT_NOISE_REL
from jaxcal.diagnosis.data.synthetic import ar1_noise, kind_of, rows_of
from jaxcal.diagnosis.kinds.signatures import signatures, zero_inputs
from jaxcal.diagnosis.kinds.table import TAU_CYCLES
from jaxcal.models.turbofan.data.flights import FlightConfig, sample_flight
from jaxcal.models.turbofan.scenario import STUDY_OUTPUTS

SHAPES = ("linear", "exponential", "piecewise")
U_MAX = 5


class Setting(NamedTuple):
    """Everything random about one record but the effect (drawn by :func:`draw`)."""

    units: int
    lives: tuple[int, ...]  # time steps (cycles) per unit
    wear: tuple[tuple, ...]  # per unit: (shape, param, end value) of the declared
    effect_shape: tuple[tuple, ...]  # per unit: (shape, param) of a parameter change
    noise_factor: float
    noise_jitter: tuple[float, ...]  # per output
    phi: float  # AR(1) coefficient of the noise
    carriers: tuple[int, ...]  # unit ids (from 1) that carry the effect
    onsets: tuple[float, ...]  # per unit: a step's onset as a share of its life
    extra: dict  # the model's own draws (operating pattern)


class StudyModel(NamedTuple):
    """One model of the study: what it declares, records and how its rows come."""

    name: str
    spec: str  # jaxcal.models.load spec
    declared: tuple[str, ...]
    outputs: tuple[str, ...]
    kinds: tuple[
        str, ...
    ]  # study labels (:func:`jaxcal.diagnosis.data.synthetic.kinds`)
    wear_end: tuple[float, float]  # the declared parameter's end value (change)
    life: tuple[int, int]
    draw_extra: Callable  # rng -> dict
    rows: Callable  # (setting, rng) -> (w [N, W], unit [N], cycle [N], frac [N])


def wear_shape(shape: str, param: float, t: np.ndarray) -> np.ndarray:
    """Share of the end-of-life change reached at life fraction ``t`` in [0, 1]:
    linear ``t``; exponential ``(e^(b t) - 1) / (e^b - 1)`` (b = param); piecewise:
    a slow phase to 20 % of the change until the knee ``t0`` (param), then linear."""
    if shape == "linear":
        return t
    if shape == "exponential":
        return np.expm1(param * t) / np.expm1(param)
    slow = 0.2 * t / param
    return np.where(t < param, slow, 0.2 + 0.8 * (t - param) / (1.0 - param))


def _shape(rng) -> tuple:
    shape = str(rng.choice(SHAPES))
    param = {"linear": 0.0, "exponential": rng.uniform(2.0, 5.0),
             "piecewise": rng.uniform(0.2, 0.6)}[shape]  # fmt: skip
    return shape, float(param)


def draw(sm: StudyModel, rng: np.random.Generator, max_units: int = U_MAX,
         max_life: int | None = None) -> Setting:  # fmt: skip
    """One random record setting of ``sm`` (module docstring); ``max_units`` /
    ``max_life`` shrink it for tests."""
    units = int(rng.integers(2, min(max_units, U_MAX) + 1))
    lo, hi = sm.life
    hi = hi if max_life is None else min(hi, max_life)
    lo = min(lo, hi)
    k = int(rng.integers(1, units + 1))
    carriers = tuple(sorted(int(u) + 1 for u in rng.choice(units, k, replace=False)))
    phi = 0.0 if rng.uniform() < 1.0 / 3.0 else float(rng.uniform(0.3, 0.8))
    return Setting(
        units=units,
        lives=tuple(int(c) for c in rng.integers(lo, hi + 1, units)),
        wear=tuple(
            (*_shape(rng), float(rng.uniform(*sm.wear_end))) for _ in range(units)
        ),  # fmt: skip
        effect_shape=tuple(_shape(rng) for _ in range(units)),
        noise_factor=float(np.exp(rng.uniform(np.log(0.5), np.log(2.0)))),
        noise_jitter=tuple(
            float(v)
            for v in np.exp(rng.uniform(np.log(0.8), np.log(1.25), len(sm.outputs)))
        ),  # fmt: skip
        phi=phi,
        carriers=carriers,
        onsets=tuple(float(v) for v in rng.uniform(0.3, 0.7, units)),
        extra=sm.draw_extra(rng),
    )


def _per_row(per_unit: tuple, u0: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """Each row's share of its unit's change (``per_unit``: (shape, param, ...))."""
    param = np.asarray([float(e[1]) for e in per_unit])[u0]
    shape = np.asarray([SHAPES.index(e[0]) for e in per_unit])[u0]
    safe = np.where(shape == 0, 0.5, param)  # keeps the unused branches finite
    return np.choose(shape, [wear_shape(s, safe, frac) for s in SHAPES])


def make_record(model, sm: StudyModel, setting: Setting, kind: str, target: str,
                size: float, seed: int, noise: bool = True):  # fmt: skip
    """One Dataset with ``kind`` of physical ``size`` on ``target`` in the carriers.

    ``size`` is in the kind's physical unit (:mod:`jaxcal.diagnosis.kinds.table`): a
    parameter's change at the end of the carrier's life (``parameter``) or its jump
    (``parameter_step``), a registered effect's value, a sensor's bias, relative gain,
    drift per TAU_CYCLES cycles or step. ``noise=False`` gives the noise-free record
    (detectability).

    Returns:
        ``(Dataset, noise std per output [S], onset cycle per carrier)``.
    """
    rng = np.random.default_rng([seed, 11])
    w, unit, cycle, frac = sm.rows(setting, rng)
    u0 = unit - 1
    theta = np.tile(np.asarray(model.nominal, np.float64), (w.shape[0], 1))
    p = model.parameter_names.index(sm.declared[0])  # the one wearing parameter
    ends = np.asarray([float(e[2]) for e in setting.wear])[u0]
    theta[:, p] += ends * (0.05 + 0.95 * _per_row(setting.wear, u0, frac))
    carry = np.isin(unit, np.asarray(setting.carriers))
    onset_cycle = {
        u: float(cycle[unit == u][int(round(setting.onsets[u - 1] *
                                            (np.sum(unit == u) - 1)))])
        for u in setting.carriers
    }  # fmt: skip
    step_on = carry & (cycle >= np.array([onset_cycle.get(int(v), np.inf)
                                          for v in unit]))  # fmt: skip
    sidx = model.output_index(sm.outputs)
    rows = rows_of(w, unit, sidx)
    inputs = zero_inputs(model, w.shape[0], rows.num_units)._replace(theta=theta)
    clean = signatures(model, rows, inputs)
    if kind != "none":
        spec = kind_of(model, kind)
        profile = {
            "constant": carry * 1.0,
            "drift": carry * (cycle - 1) / TAU_CYCLES,
            "step": step_on * 1.0,
            "spline": carry * _per_row(setting.effect_shape, u0, frac),
        }[spec.profile]
        channel = spec.channel
        if channel == "parameter":
            inputs.theta[:, model.parameter_names.index(target)] += size * profile
        elif channel == "effect":
            e = [x.name for x in model.effects].index(target)
            inputs.effects[:, e] += size * profile
        elif channel == "condition":
            inputs.w_offset[:, model.condition_names.index(target)] += size * profile
        else:
            field = inputs.additive if channel == "additive" else inputs.multiplicative
            field[:, model.output_index([target])[0]] += size * profile
    sig = signatures(model, rows, inputs) if kind != "none" else clean
    x, ok = sig.y, sig.ok & clean.ok
    rel = model.diagnosis.noise_rel or {}
    level = np.abs(clean.y).mean(0)
    ref = np.array([rel.get(s, DEFAULT_NOISE_REL) for s in sm.outputs]) * level
    std = ref * setting.noise_factor * np.asarray(setting.noise_jitter)
    if noise:
        x = x + std * ar1_noise(np.random.default_rng([seed, 12]), x.shape, unit,
                                setting.phi)  # fmt: skip
    if model.is_stateful:  # a series is kept whole: a bad row is masked, not cut
        x = np.where(ok[:, None], x, np.nan)
        ok = np.ones_like(ok)
    data = Dataset(
        w=w[ok], x=x[ok], condition_names=model.condition_names,
        output_names=tuple(sm.outputs), unit=unit[ok], time=cycle[ok].astype(float),
        theta=theta[ok], theta_names=model.parameter_names, source=f"robust:{kind}",
    )  # fmt: skip
    return data, std, onset_cycle


# ------------------------------------------------------------------ the turbofan

C_MAX = 110  # fixed pool shape: one compilation per profile family
PROFILES = {
    "short_haul": FlightConfig(
        dt_s=60.0,
        class_hours=((0.8, 1.5), (1.5, 2.5), (2.5, 3.5)),
        cruise_alt_short_ft=(18_000.0, 25_000.0),
        cruise_tra=(55.0, 72.0),
        cruise_mach_short=(0.58, 0.66),
    ),
    "default": FlightConfig(dt_s=60.0),
    "long_haul": FlightConfig(
        dt_s=60.0,
        class_hours=((4.0, 6.0), (6.0, 8.0), (8.0, 9.0)),
        cruise_tra=(66.0, 82.0),
        delta_t_day_r=24.0,
    ),
}


@functools.partial(jax.jit, static_argnums=(2,))
def _flights(key, classes, cfg: FlightConfig):
    """Flights of the fixed pool [U_MAX, C_MAX]: w [U, C, T, 4], mask [U, C, T]."""
    keys = jax.random.split(key, (U_MAX, C_MAX))
    f = jax.vmap(lambda ku, c: jax.vmap(lambda k: sample_flight(k, c, cfg))(ku))(
        keys, classes
    )
    return f.w, f.mask


def _turbofan_extra(rng) -> dict:
    return {
        "profile": str(rng.choice(list(PROFILES))),
        "classes": [int(c) for c in rng.integers(1, 4, U_MAX)],
        "rows_per_cycle": int(rng.integers(1, 4)),
        "stride": int(rng.integers(1, 3)),
    }


def _turbofan_rows(setting: Setting, rng):
    """Conditions, unit, cycle and life fraction of the kept flight samples."""
    ex = setting.extra
    key = jax.random.key(int(rng.integers(2**31)))
    w, mask = (
        np.asarray(a)
        for a in _flights(
            key, jnp.asarray(ex["classes"], jnp.int32), PROFILES[ex["profile"]]
        )
    )
    scores = np.where(mask, rng.uniform(size=mask.shape), -1.0)
    picks = np.argsort(-scores, axis=-1)[..., : ex["rows_per_cycle"]]
    u_i, c_i = np.meshgrid(np.arange(U_MAX), np.arange(C_MAX), indexing="ij")
    life = np.asarray(setting.lives + (0,) * (U_MAX - setting.units))[:, None]
    keep = (c_i < life) & (c_i % ex["stride"] == 0)
    u_k, c_k = u_i[keep], c_i[keep]  # unit-major, then cycle: the time order
    k = picks[u_k, c_k]  # [M, R]
    u_r, c_r = np.repeat(u_k, k.shape[1]), np.repeat(c_k, k.shape[1])
    frac = (c_r + 1) / np.asarray(setting.lives)[u_r]
    return w[u_r, c_r, k.ravel()], u_r + 1, c_r + 1, frac


# ---------------------------------------------------------- heat exchanger, thermal


def _wander(rng, n, low, high, step=0.02):
    """A slow random walk inside ``[low, high]`` (reflected), ``[n, len(low)]``."""
    low, high = np.asarray(low), np.asarray(high)
    span = high - low
    x = np.empty((n, low.size))
    x[0] = low + span * rng.uniform(0.3, 0.7, low.size)
    for t in range(1, n):
        x[t] = x[t - 1] + step * span * rng.standard_normal(low.size)
        x[t] = np.where(x[t] < low, 2 * low - x[t], x[t])
        x[t] = np.where(x[t] > high, 2 * high - x[t], x[t])
    return x


def _unit_rows(setting: Setting, make_w, rng):
    ws, units, cycles, fracs = [], [], [], []
    for u, life in enumerate(setting.lives):
        ws.append(make_w(life, rng))
        units.append(np.full(life, u + 1))
        cycles.append(np.arange(1, life + 1))
        fracs.append(np.arange(1, life + 1) / life)
    return (np.concatenate(ws), np.concatenate(units), np.concatenate(cycles),
            np.concatenate(fracs))  # fmt: skip


def _hx_rows(setting: Setting, rng):
    """Operating points wandering slowly in the middle of the rated range, with a
    little per-sample jitter."""
    from jaxcal.models.heat_exchanger import CONDITION_RANGE

    low, high = (np.asarray(b) for b in CONDITION_RANGE)
    lo, hi = low + 0.2 * (high - low), high - 0.2 * (high - low)

    def make_w(n, rng):
        return _wander(rng, n, lo, hi) * (1 + 0.003 * rng.standard_normal((n, 4)))

    return _unit_rows(setting, make_w, rng)


def _thermal_rows(setting: Setting, rng):
    """A heater switched between random levels every 10-40 samples; the ambient
    wandering slowly."""

    def make_w(n, rng):
        power, t = np.empty(n), 0
        while t < n:
            d = int(rng.integers(10, 41))
            power[t : t + d] = rng.uniform(300.0, 2500.0)
            t += d
        ambient = _wander(rng, n, [275.0], [300.0], step=0.01)[:, 0]
        return np.stack([power, ambient], axis=1)

    return _unit_rows(setting, make_w, rng)


SENSOR_KINDS = ("sensor_bias", "sensor_gain", "sensor_drift", "sensor_gain_drift",
                "sensor_step")  # fmt: skip
STUDY_MODELS = {
    "turbofan": StudyModel(
        "turbofan", "cmapss", ("HPT_eff_mod",), STUDY_OUTPUTS,
        ("parameter", "parameter_step", "t2_offset", *SENSOR_KINDS),
        (-0.019, -0.0065), (30, C_MAX), _turbofan_extra, _turbofan_rows,
    ),
    "heat_exchanger": StudyModel(
        "heat_exchanger", "heat_exchanger", ("fouling",),
        ("T_hot_out", "T_cold_out", "dp_hot", "duty"),
        ("parameter", "parameter_step", *SENSOR_KINDS),
        (0.1, 0.4), (60, 200), lambda rng: {}, _hx_rows,
    ),
    "thermal": StudyModel(
        "thermal", "thermal", ("R_sa",), ("T_core", "T_shell", "q_loss"),
        ("parameter", "parameter_step", *SENSOR_KINDS),
        (-0.006, -0.002), (150, 400), lambda rng: {}, _thermal_rows,
    ),
}  # fmt: skip
