"""Randomised turbofan fleets for the robust identification study (loop_robust.py).

The diagnosis is built on assumptions that the project's own generator
(:mod:`jaxcal.diagnosis.synthetic` on :mod:`jaxcal.models.turbofan_scenario`) shares:
one flight-profile family, lives from the ground-truth degradation law, white noise at
the reference level, every unit carrying the effect. Here each record draws what the
diagnosis does *not* assume (:func:`draw_setting`):

* the flight-profile family (:data:`PROFILES`: short-haul, the default, long-haul) and
  each unit's flight class;
* the number of units (2-5), each unit's life (30-110 cycles), samples kept per flight
  (1-3) and cycle stride (1-2);
* the shape of the declared modifier's wear (linear, exponential, piecewise-linear
  with a knee; :func:`wear_shape`) and its end value;
* the noise level (0.5x-2x the reference, log-uniform, with a per-sensor jitter of
  0.8x-1.25x) and colour: AR(1) along each unit's rows with coefficient 0 (one record
  in three) or 0.3-0.8, scaled to keep the marginal std (:func:`ar1_noise`);
* which units carry the effect (1 to all of them, a random subset).

:func:`make_record` then puts one effect of a given kind and physical size on the
carriers through the extended model (:func:`jaxcal.diagnosis.effects.linearize`) and
adds the noise.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.data.flights import FlightConfig, sample_flight
from jaxcal.diagnosis.effects import LAYER_NAMES, TAU_CYCLES, linearize
from jaxcal.diagnosis.prepare import DEFAULT_NOISE_REL

U_MAX, C_MAX = 5, 110  # fixed pool shape: one compilation per profile family
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
SHAPES = ("linear", "exponential", "piecewise")
DECLARED_EOL = (-0.019, -0.0065)  # HPT_eff_mod end of life (ground_truth.py)


class Setting(NamedTuple):
    """Everything random about one record but the effect (drawn by draw_setting)."""

    profile: str
    units: int
    classes: tuple[int, ...]  # flight class per unit
    lives: tuple[int, ...]  # cycles per unit
    rows_per_cycle: int
    stride: int
    wear: tuple[tuple, ...]  # per unit: (shape, param, end value) of the declared
    effect_shape: tuple[tuple, ...]  # per unit: (shape, param) of a parameter effect
    noise_factor: float
    noise_jitter: tuple[float, ...]  # per sensor
    phi: float  # AR(1) coefficient of the noise
    carriers: tuple[int, ...]  # unit ids (from 1) that carry the effect


def reference_setting(num_sensors: int, max_life: int = C_MAX) -> Setting:
    """The nominal record the detectability sizes are computed on: the default
    profile, 3 units of 80 cycles, 2 samples per flight, linear wear, white noise
    at the reference level, every unit carrying."""
    return Setting(
        "default", 3, (1, 2, 3), (min(80, max_life),) * 3, 2, 1,
        (("linear", 0.0, -0.012),) * 3, (("linear", 0.0),) * 3,
        1.0, (1.0,) * num_sensors, 0.0, (1, 2, 3),
    )  # fmt: skip


def _shape(rng) -> tuple:
    shape = str(rng.choice(SHAPES))
    param = {"linear": 0.0, "exponential": rng.uniform(2.0, 5.0),
             "piecewise": rng.uniform(0.2, 0.6)}[shape]  # fmt: skip
    return shape, float(param)


def draw_setting(
    rng: np.random.Generator,
    num_sensors: int,
    max_units: int = U_MAX,
    max_life: int = C_MAX,
) -> Setting:
    """One random record setting (module docstring); ``max_units`` / ``max_life``
    shrink it for tests."""
    units = int(rng.integers(2, min(max_units, U_MAX) + 1))
    max_life = min(max_life, C_MAX)
    k = int(rng.integers(1, units + 1))
    carriers = tuple(sorted(int(u) + 1 for u in rng.choice(units, k, replace=False)))
    wear = tuple(
        (*_shape(rng), float(rng.uniform(*DECLARED_EOL))) for _ in range(units)
    )
    phi = 0.0 if rng.uniform() < 1.0 / 3.0 else float(rng.uniform(0.3, 0.8))
    return Setting(
        profile=str(rng.choice(list(PROFILES))),
        units=units,
        classes=tuple(int(c) for c in rng.integers(1, 4, units)),
        lives=tuple(
            int(c) for c in rng.integers(min(30, max_life), max_life + 1, units)
        ),
        rows_per_cycle=int(rng.integers(1, 4)),
        stride=int(rng.integers(1, 3)),
        wear=wear,
        effect_shape=tuple(_shape(rng) for _ in range(units)),
        noise_factor=float(np.exp(rng.uniform(np.log(0.5), np.log(2.0)))),
        noise_jitter=tuple(
            float(v)
            for v in np.exp(rng.uniform(np.log(0.8), np.log(1.25), num_sensors))
        ),
        phi=phi,
        carriers=carriers,
    )


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


@functools.partial(jax.jit, static_argnums=(2,))
def _flights(key, classes, cfg: FlightConfig):
    """Flights of the fixed pool [U_MAX, C_MAX]: w [U, C, T, 4], mask [U, C, T]."""
    keys = jax.random.split(key, (U_MAX, C_MAX))
    f = jax.vmap(lambda ku, c: jax.vmap(lambda k: sample_flight(k, c, cfg))(ku))(
        keys, classes
    )
    return f.w, f.mask


@jax.jit
def ar1_noise(key, std, phi, start):
    """AR(1) noise along rows ``e_t = phi e_(t-1) + sqrt(1 - phi^2) std eps_t``,
    restarted from the stationary law where ``start`` (each unit's first row), so
    the marginal std is ``std`` for any ``phi``: ``[N, S]``."""
    eps = jax.random.normal(key, (start.shape[0], std.shape[0]), jnp.float64) * std
    scale = jnp.sqrt(1.0 - phi**2)

    def step(prev, inp):
        e, first = inp
        cur = jnp.where(first, e, phi * prev + scale * e)
        return cur, cur

    _, out = jax.lax.scan(step, jnp.zeros_like(std), (eps, start))
    return out


def _rows(setting: Setting, key):
    """Conditions, unit, cycle and life fraction of the kept rows."""
    classes = np.ones(U_MAX, np.int32)
    classes[: setting.units] = setting.classes
    w, mask = (np.asarray(a) for a in _flights(key, jnp.asarray(classes),
                                               PROFILES[setting.profile]))  # fmt: skip
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel())
    scores = np.where(mask, rng.uniform(size=mask.shape), -1.0)
    picks = np.argsort(-scores, axis=-1)[..., : setting.rows_per_cycle]
    u_i, c_i = np.meshgrid(np.arange(U_MAX), np.arange(C_MAX), indexing="ij")
    life = np.asarray(setting.lives + (0,) * (U_MAX - setting.units))[:, None]
    keep = (c_i < life) & (c_i % setting.stride == 0)
    u_k, c_k = u_i[keep], c_i[keep]  # unit-major, then cycle: the time order
    k = picks[u_k, c_k]  # [M, R]
    u_r = np.repeat(u_k, k.shape[1])
    c_r = np.repeat(c_k, k.shape[1])
    w_r = w[u_r, c_r, k.ravel()]
    frac = (c_r + 1) / np.asarray(setting.lives)[u_r]
    return w_r, u_r + 1, c_r + 1, frac


def _per_row(per_unit: tuple, u0: np.ndarray, frac: np.ndarray, ends=False):
    """Each row's wear share (or, with ``ends``, its unit's end value)."""
    if ends:
        return np.asarray([float(e[2]) for e in per_unit])[u0]
    param = np.asarray([float(e[1]) for e in per_unit])[u0]
    shape = np.asarray([SHAPES.index(e[0]) for e in per_unit])[u0]
    safe = np.where(shape == 0, 0.5, param)  # keeps the unused branches finite
    return np.choose(shape, [wear_shape(s, safe, frac) for s in SHAPES])


def make_record(model, setting: Setting, kind: str, target: str, size: float,
                key, sensors, declared=("HPT_eff_mod",), noise=True):  # fmt: skip
    """One Dataset with ``kind`` of physical ``size`` on ``target`` in the carriers.

    Kinds: ``none``, ``parameter`` (target an undeclared parameter, ``size`` its end
    value, following each carrier's ``effect_shape``), a registered effect of the
    model (target = kind), or an output layer (``sensor_bias`` ... on output
    ``target``; a gain as a fraction of the output, drifts per TAU_CYCLES cycles).
    ``noise=False`` gives the noise-free record (detectability probes).

    Returns:
        ``(Dataset, the noise std per sensor [S])``.
    """
    key_rows, key_noise = jax.random.split(key)
    w, unit, cycle, frac = _rows(setting, key_rows)
    theta = np.tile(np.asarray(model.nominal, np.float64), (w.shape[0], 1))
    u0 = unit - 1
    p = model.parameter_names.index(declared[0])  # the one wearing modifier
    theta[:, p] += _per_row(setting.wear, u0, frac, ends=True) * (
        0.05 + 0.95 * _per_row(setting.wear, u0, frac)
    )
    carry = np.isin(unit, np.asarray(setting.carriers))
    effects = np.zeros(len(model.effects))
    layer = np.zeros((len(LAYER_NAMES), len(model.outputs)))
    sidx = model.output_index(sensors)
    tau = (cycle - 1) / TAU_CYCLES
    if kind == "parameter":
        p = model.parameter_names.index(target)
        theta[:, p] += carry * size * _per_row(setting.effect_shape, u0, frac)
    elif kind in [e.name for e in model.effects]:
        effects[[e.name for e in model.effects].index(kind)] = size
    elif kind in LAYER_NAMES:
        layer[LAYER_NAMES.index(kind), model.output_index([target])[0]] = size
    elif kind != "none":
        raise ValueError(f"kind {kind!r}: not none, parameter, an effect or a layer")
    clean = linearize(model, w, theta, np.zeros_like(effects), 0.0 * layer, tau)
    y = linearize(model, w, theta, effects, layer, tau) if kind != "none" else clean
    x = np.where(carry[:, None], y.y, clean.y)[:, sidx]
    ok = np.where(carry, y.ok, True) & clean.ok
    rel = model.diagnosis.noise_rel or {}
    level = np.abs(clean.y[:, sidx]).mean(0)
    ref = np.array([rel.get(s, DEFAULT_NOISE_REL) for s in sensors]) * level
    std = ref * setting.noise_factor * np.asarray(setting.noise_jitter)
    if noise:
        start = np.r_[True, unit[1:] != unit[:-1]]
        x = x + np.asarray(ar1_noise(key_noise, jnp.asarray(std), setting.phi,
                                     jnp.asarray(start)))  # fmt: skip
    data = Dataset(
        w=w[ok], x=x[ok], condition_names=model.condition_names,
        output_names=tuple(sensors), unit=unit[ok], time=cycle[ok].astype(float),
        theta=theta[ok], theta_names=model.parameter_names, source=f"robust:{kind}",
    )  # fmt: skip
    return data, std
