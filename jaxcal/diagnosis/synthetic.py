"""Test records with exactly one undeclared effect of a chosen kind.

A record is an N-CMAPSS-like fleet: each unit flies a run-to-failure life
(:func:`jaxcal.data.degradation.sample_unit_degradation`, the declared modifiers degrade
with the unit's health index) and every cycle is a climb / cruise / descent flight
(:func:`jaxcal.data.flights.sample_flight`) from which ``rows_per_cycle`` random
recorded samples are kept, so that a record holds a realistic number of cycles at a
size a test can afford. Sensors are the extended engine model
(:mod:`jaxcal.diagnosis.effects`) with one effect switched on, plus white Gaussian noise of
the C-MAPSS relative level of each sensor (:func:`.problem.reference_noise_rel`).

Effect kinds (:data:`KINDS`) and the size ranges they are drawn from
(:data:`EFFECT_SIZES`, magnitude uniform in the range, sign as noted):

* ``none``: the clean record (false-alarm runs);
* ``health``: an undeclared modifier degrading with the unit's health index to an
  end-of-life value in -2 % ... -0.5 %;
* the six engine effects, constant over the record;
* ``sensor_bias`` / ``sensor_gain`` / ``sensor_drift`` on a random sensor, sized in
  multiples of its noise std (a gain relative to the sensor's mean level, a drift per
  100 cycles since the unit's first cycle);
* ``discrepancy``: an effect outside the library, a smooth bump in Mach added to one
  sensor, ``A sigma exp(-((M - m0) / 0.12)^2)``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.data.degradation import DegradationConfig, sample_unit_degradation
from jaxcal.data.flights import FlightConfig, sample_flight
from jaxcal.data.record import Record
from jaxcal.diagnosis.effects import (
    ENGINE_EFFECT_SCALE,
    LAYER_NAMES,
    TAU_CYCLES,
    candidate_name,
    linearize,
    sensor_unit,
)
from jaxcal.diagnosis.noise import reference_noise_rel
from jaxcal.physics.constants import HEALTH_NAMES, MEASURED_SENSOR_NAMES
from jaxcal.typedefs import PRNGKey

ENGINE_KINDS = (
    "t2_offset",
    "customer_bleed",
    "power_offtake",
    "core_nozzle_area",
    "bypass_nozzle_area",
    "inlet_recovery",
)
KINDS = ("none", "health", *ENGINE_KINDS, *LAYER_NAMES, "discrepancy")

# kind -> ((low, high) magnitude, sign): +1 positive, -1 negative, 0 random sign.
EFFECT_SIZES: dict[str, tuple[tuple[float, float], int]] = {
    "health": ((0.005, 0.02), -1),  # end-of-life value of the modifier
    "t2_offset": ((1.0, 3.0), 0),  # degR
    "customer_bleed": ((0.005, 0.02), 1),  # fraction of W25
    "power_offtake": ((150.0, 500.0), 1),  # hp
    "core_nozzle_area": ((0.01, 0.03), 0),  # relative
    "bypass_nozzle_area": ((0.01, 0.03), 0),  # relative
    "inlet_recovery": ((0.003, 0.01), -1),  # P2/Pt0
    "sensor_bias": ((2.0, 5.0), 0),  # noise std
    "sensor_gain": ((2.0, 5.0), 0),  # noise std / mean level
    "sensor_drift": ((3.0, 6.0), 0),  # noise std per 100 cycles
    "discrepancy": ((3.0, 6.0), 0),  # noise std (bump height)
}


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
    """Static settings of :func:`make_synthetic_record`."""

    num_units: int = 3
    rows_per_cycle: int = 2  # recorded samples kept per flight
    cycle_stride: int = 1  # keep every k-th cycle of each life
    declared: tuple[str, ...] = ("HPT_eff_mod",)  # modifiers that degrade (calibrated)
    sensors: tuple[str, ...] = tuple(s for s in MEASURED_SENSOR_NAMES if s != "Nf")
    noise_scale: float = 1.0  # multiplies the reference noise levels
    flight: FlightConfig = FlightConfig(dt_s=60.0)  # 1-min samples are plenty here

    def __post_init__(self):
        if self.num_units < 1 or self.rows_per_cycle < 1 or self.cycle_stride < 1:
            raise ValueError(
                "SyntheticConfig: num_units, rows_per_cycle, cycle_stride >= 1"
            )
        if not self.noise_scale > 0:
            raise ValueError("SyntheticConfig.noise_scale must be > 0")


class EffectTruth(NamedTuple):
    """The effect put into a record."""

    kind: str  # one of KINDS
    name: str  # the library candidate's name ("" for none, "discrepancy[<s>]")
    target: str  # sensor, health modifier or engine effect ("" for none)
    size: float  # physical units (see EFFECT_SIZES)
    unit: str


class SyntheticRecord(NamedTuple):
    """A generated record, the noise it got and the effect it contains."""

    record: Record
    noise_std: dict  # sensor -> std used for the noise
    truth: EffectTruth


@functools.partial(jax.jit, static_argnums=(2, 3))
def _sample_fleet(key_deg, key_flight, deg_cfg, flight_cfg, classes):
    """Degradation per unit [U, C] and one flight per (unit, cycle) [U, C, T]."""
    c_max = deg_cfg.max_eol_cycle
    deg = jax.vmap(lambda k, fc: sample_unit_degradation(k, c_max, deg_cfg, fc))(
        jax.random.split(key_deg, classes.shape[0]), classes
    )
    keys = jax.random.split(key_flight, (classes.shape[0], c_max))
    flights = jax.vmap(
        lambda ku, fc: jax.vmap(lambda k: sample_flight(k, fc, flight_cfg))(ku)
    )(keys, classes)
    return deg, flights


def _pick(rng: np.random.Generator, kind: str, sensors, declared) -> tuple[str, float]:
    (lo, hi), sign = EFFECT_SIZES[kind]
    size = rng.uniform(lo, hi) * (sign if sign else rng.choice([-1.0, 1.0]))
    if kind == "health":
        target = str(rng.choice([h for h in HEALTH_NAMES if h not in declared]))
    elif kind in LAYER_NAMES or kind == "discrepancy":
        target = str(rng.choice(list(sensors)))
    else:
        target = kind
    return target, float(size)


def make_synthetic_record(
    key: PRNGKey,
    engine,
    kind: str,
    cfg: SyntheticConfig,
    *,
    target: str | None = None,
    size: float | None = None,
) -> SyntheticRecord:
    """One record with exactly one undeclared effect of ``kind`` (module docstring).

    Args:
        key: PRNG key (the same key gives the same record).
        engine: the engine model.
        kind: one of :data:`KINDS`.
        cfg: static settings.
        target: force the sensor / modifier the effect acts on (default: random).
        size: force the size, in the units of :data:`EFFECT_SIZES` (default: drawn).

    Returns:
        :class:`SyntheticRecord` with the record, the noise levels and the truth.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown effect kind {kind!r}; valid: {', '.join(KINDS)}")
    valid_targets = {
        "health": [h for h in HEALTH_NAMES if h not in cfg.declared],
        "discrepancy": cfg.sensors,
        **{f: cfg.sensors for f in LAYER_NAMES},
    }
    if target is not None and target not in valid_targets.get(kind, ()):
        raise ValueError(
            f"target={target!r} is not valid for kind {kind!r}; valid: "
            f"{list(valid_targets.get(kind, ()))}"
        )
    key_class, key_deg, key_flight, key_rows, key_effect, key_noise = jax.random.split(
        key, 6
    )
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key_effect)).ravel())
    tgt, size_drawn = (
        ("", 0.0) if kind == "none" else _pick(rng, kind, cfg.sensors, cfg.declared)
    )
    tgt = target or tgt
    size = size if size is not None else size_drawn
    deg_cfg = DegradationConfig(degrading=cfg.declared)
    classes = jax.random.randint(key_class, (cfg.num_units,), 1, 4)
    deg, flights = _sample_fleet(key_deg, key_flight, deg_cfg, cfg.flight, classes)
    scores = jnp.where(
        flights.mask, jax.random.uniform(key_rows, flights.mask.shape), -1.0
    )
    picks = np.asarray(jnp.argsort(-scores, axis=-1)[..., : cfg.rows_per_cycle])
    eol = np.asarray(deg.eol_cycle)
    rows = [
        (u, c, k)
        for u in range(cfg.num_units)
        for c in range(0, int(eol[u]), cfg.cycle_stride)
        for k in picks[u, c]
    ]
    u_i, c_i, k_i = (np.array(a) for a in zip(*rows, strict=True))
    w = np.asarray(flights.w)[u_i, c_i, k_i]
    theta = np.asarray(deg.theta)[u_i, c_i].copy()
    if kind == "health":  # degrades with the unit's health index, like the declared
        theta[:, HEALTH_NAMES.index(tgt)] = size * (
            1.0 - np.asarray(deg.health)[u_i, c_i]
        )
    cycle = np.asarray(deg.cycle)[u_i, c_i]
    effects = np.zeros(len(engine.effect_names))
    layer = np.zeros((len(LAYER_NAMES), len(engine.sensor_names)))
    sidx = [list(engine.sensor_names).index(s) for s in cfg.sensors]
    tau = (cycle - 1) / TAU_CYCLES  # every life starts at cycle 1
    clean = linearize(engine, w, theta, effects, layer, tau).y[:, sidx]
    level = np.abs(clean).mean(0)
    std = (
        np.array([reference_noise_rel(s) for s in cfg.sensors])
        * level
        * cfg.noise_scale
    )
    unit = "-"
    if kind in ENGINE_KINDS:
        effects[list(engine.effect_names).index(kind)] = size
        unit = ENGINE_EFFECT_SCALE[kind][1]
    elif kind in LAYER_NAMES:
        s = list(cfg.sensors).index(tgt)
        scale = std[s] / level[s] if kind == "sensor_gain" else std[s]
        size = size * scale
        layer[LAYER_NAMES.index(kind), sidx[s]] = size
        unit = "-" if kind == "sensor_gain" else sensor_unit(tgt)
    y = linearize(engine, w, theta, effects, layer, tau)
    x = y.y[:, sidx]
    if kind == "discrepancy":
        s = list(cfg.sensors).index(tgt)
        m0 = rng.uniform(0.45, 0.65)
        size = size * std[s]
        x[:, s] += size * np.exp(-(((w[:, 1] - m0) / 0.12) ** 2))
        unit = sensor_unit(tgt)
    noise = np.asarray(jax.random.normal(key_noise, x.shape, dtype=jnp.float64))
    x = x + std * noise
    ok = y.ok
    record = Record(
        w=w[ok],
        x=x[ok],
        x_names=cfg.sensors,
        theta=theta[ok],
        unit=u_i[ok] + 1,
        cycle=cycle[ok],
        flight_class=np.asarray(classes)[u_i[ok]].astype(float),
        hs=np.asarray(deg.hs)[u_i, c_i][ok].astype(float),
        rul=np.asarray(deg.rul)[u_i, c_i][ok],
        source=f"synthetic:{kind}",
    )
    name = {"none": "", "discrepancy": f"discrepancy[{tgt}]"}.get(
        kind, candidate_name("engine" if kind in ENGINE_KINDS else kind, tgt)
    )
    truth = EffectTruth(kind, name, tgt, float(size), unit)
    return SyntheticRecord(
        record, dict(zip(cfg.sensors, std.tolist(), strict=True)), truth
    )
