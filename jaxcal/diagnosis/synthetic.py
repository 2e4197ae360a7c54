"""Test data sets with exactly one undeclared effect of a chosen kind, for any model.

A *scenario* supplies the clean rows: conditions, all parameters (the declared ones
drifting with a per-row health index), unit and cycle (e.g.
:func:`jaxcal.models.turbofan_scenario.make_scenario` flies N-CMAPSS-like lives). This
module switches one effect on in the extended model of :mod:`.effects`, adds white
Gaussian noise at the model's reference relative level per output
(``DiagnosisHints.noise_rel``, times ``noise_scale``) and returns a
:class:`~jaxcal.data.dataset.Dataset` with the truth.

Effect kinds (:func:`kinds`), drawn from ``SyntheticConfig.sizes`` (magnitude uniform
in the range, sign as noted; defaults :func:`default_sizes`):

* ``none``: the clean data (false-alarm runs);
* ``parameter``: an undeclared parameter drifting from nominal with the unit's health
  index to an end value in the range;
* each registered effect of the model (``model.effects``), constant over the data;
* ``sensor_bias`` / ``sensor_gain`` / ``sensor_drift`` / ``sensor_gain_drift`` on a
  random output, sized in multiples of its noise std (a gain relative to the output's
  mean level, a drift per 100 cycles since the unit's first cycle; the gain drift is
  the multiplicative one);
* ``discrepancy``: an effect outside the library, a smooth bump in one condition
  added to one output, ``A sigma exp(-((w_c - c0) / width)^2)``
  (``SyntheticConfig.bump``);
* ``condition_offset`` (only if the model allows condition offsets): a logged
  condition off by a constant, in multiples of the condition's spread.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.diagnosis.effects import (
    LAYER_NAMES,
    TAU_CYCLES,
    candidate_name,
    linearize,
    natural_scale,
    offset_conditions,
)
from jaxcal.diagnosis.prepare import DEFAULT_NOISE_REL
from jaxcal.model import Model
from jaxcal.typedefs import PRNGKey


def kinds(model: Model) -> tuple[str, ...]:
    """The effect kinds a synthetic data set of ``model`` can hold (module doc)."""
    extra = ("condition_offset",) if offset_conditions(model) else ()
    # later additions go last, so that the position of the older kinds (which seeds
    # the study's records) does not move
    return (
        "none", "parameter", *(e.name for e in model.effects), *LAYER_NAMES[:3],
        "discrepancy", *LAYER_NAMES[3:], *extra,
    )  # fmt: skip


def default_sizes(model: Model) -> dict[str, tuple[tuple[float, float], int]]:
    """kind -> ((low, high) magnitude, sign); sign +1, -1 or 0 (random).

    Parameters and registered effects: 0.5 to 2 natural steps
    (:func:`.effects.natural_scale`; the parameter's drift is taken by its natural
    step for every undeclared parameter alike); output layers: 2 to 5 noise std (3 to
    6 for a drift); the discrepancy bump: 3 to 6 noise std; a condition offset: 0.5 to
    2 % of the condition's spread (x100 below).
    """
    sizes = {e.name: ((0.5 * s, 2.0 * s), 0) for e in model.effects
             for s in [natural_scale(model, e.name)]}  # fmt: skip
    return {
        "parameter": ((0.5, 2.0), 0),  # natural steps of the chosen parameter
        **sizes,
        "sensor_bias": ((2.0, 5.0), 0),
        "sensor_gain": ((2.0, 5.0), 0),
        "sensor_drift": ((3.0, 6.0), 0),
        "sensor_gain_drift": ((3.0, 6.0), 0),
        "discrepancy": ((3.0, 6.0), 0),
        "condition_offset": ((0.5, 2.0), 0),  # % of the condition's std
    }


class Scenario(NamedTuple):
    """Clean rows of a synthetic data set (``N`` rows)."""

    w: np.ndarray  # [N, W]
    theta: np.ndarray  # [N, P_all] (the declared parameters drifting)
    unit: np.ndarray  # [N] int
    cycle: np.ndarray  # [N] cycle (time) index; every life starts at cycle 1
    health: np.ndarray  # [N] health index, 1 new -> 0 end of life


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
    """Static settings of :func:`make_synthetic_data`.

    Attributes:
        sensors: outputs recorded (default all of the model's).
        declared: parameters that drift in the scenario (the calibrated ones).
        noise_scale: multiplies the reference noise levels.
        sizes: kind -> ((low, high), sign) (default :func:`default_sizes`); the
            units of ``parameter`` are the parameter's own when ``parameter_physical``.
        parameter_physical: ``sizes["parameter"]`` is in the parameter's units
            (True) or in natural steps (False).
        bump: ``(condition, (c0_low, c0_high), width)`` of the discrepancy bump
            (default: the first condition that varies, centre between its 45th and
            65th percentile, width 20 % of its spread).
    """

    sensors: tuple[str, ...] = ()
    declared: tuple[str, ...] = ()
    noise_scale: float = 1.0
    sizes: Mapping[str, Any] | None = None
    parameter_physical: bool = False
    bump: tuple[str, tuple[float, float], float] | None = None

    def __post_init__(self):
        if not self.noise_scale > 0:
            raise ValueError("SyntheticConfig.noise_scale must be > 0")


class EffectTruth(NamedTuple):
    """The effect put into a data set."""

    kind: str  # one of kinds(model)
    name: str  # the library candidate's name ("" for none, "discrepancy[<s>]")
    target: str  # output, parameter, effect or condition ("" for none)
    size: float  # physical units (the model's)
    unit: str
    condition: str = ""  # the bump's condition (discrepancy only)
    carriers: tuple[int, ...] = ()  # unit ids that carry it (empty: every unit)


class SyntheticData(NamedTuple):
    """A generated data set, the noise it got and the effect it contains."""

    data: Dataset
    noise_std: dict  # output -> std used for the noise
    truth: EffectTruth


def _pick(rng, kind, sensors, declared, model, sizes) -> tuple[str, float]:
    (lo, hi), sign = sizes[kind]
    size = rng.uniform(lo, hi) * (sign if sign else rng.choice([-1.0, 1.0]))
    if kind == "parameter":
        free = [p for p in model.parameter_names if p not in declared]
        target = str(rng.choice(free))
    elif kind in LAYER_NAMES or kind == "discrepancy":
        target = str(rng.choice(list(sensors)))
    elif kind == "condition_offset":
        target = str(rng.choice(list(offset_conditions(model))))
    else:
        target = kind
    return target, float(size)


def make_synthetic_data(
    key: PRNGKey,
    model: Model,
    kind: str,
    cfg: SyntheticConfig,
    scenario: Callable[[jax.Array], Scenario],
    *,
    target: str | None = None,
    size: float | None = None,
    carriers=None,
) -> SyntheticData:
    """One data set with exactly one undeclared effect of ``kind`` (module docstring).

    Args:
        key: PRNG key (the same key gives the same data). It is split in six: the
            first four go to ``scenario``, then the effect and the noise.
        model: a static model (float64 enabled by the caller).
        kind: one of :func:`kinds`.
        cfg: static settings.
        scenario: ``scenario(keys [4]) -> Scenario`` (the clean rows).
        target: force the output / parameter / condition the effect acts on.
        size: force the size, in the units of ``cfg.sizes`` (default: drawn).
        carriers: unit ids that carry the effect (default every unit): a fleet in
            which only some engines have it; the others get the clean rows.

    Returns:
        :class:`SyntheticData`; rows where the model is invalid are left out.
    """
    valid_kinds = kinds(model)
    if kind not in valid_kinds:
        raise ValueError(
            f"unknown effect kind {kind!r}; valid: {', '.join(valid_kinds)}"
        )
    sensors = tuple(cfg.sensors) or model.output_names
    sizes = {**default_sizes(model), **dict(cfg.sizes or {})}
    valid_targets = {
        "parameter": [p for p in model.parameter_names if p not in cfg.declared],
        "discrepancy": sensors,
        "condition_offset": offset_conditions(model),
        **{f: sensors for f in LAYER_NAMES},
    }
    if target is not None and target not in valid_targets.get(kind, ()):
        raise ValueError(
            f"target={target!r} is not valid for kind {kind!r}; valid: "
            f"{list(valid_targets.get(kind, ()))}"
        )
    keys = jax.random.split(key, 6)
    key_effect, key_noise = keys[4], keys[5]
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key_effect)).ravel())
    tgt, size_drawn = (
        ("", 0.0) if kind == "none" else _pick(
            rng, kind, sensors, cfg.declared, model, sizes
        )
    )  # fmt: skip
    tgt = target or tgt
    size = size if size is not None else size_drawn
    scn = scenario(keys[:4])
    w, theta, cycle = scn.w, np.array(scn.theta, np.float64), scn.cycle
    if kind == "parameter":  # drifts with the unit's health index, like the declared
        j = model.parameter_names.index(tgt)
        step = 1.0 if cfg.parameter_physical else natural_scale(model, tgt)
        size = size * step
        theta[:, j] = model.nominal[j] + size * (1.0 - scn.health)
    effects = np.zeros(len(model.effects))
    layer = np.zeros((len(LAYER_NAMES), len(model.outputs)))
    w_offset = np.zeros(len(model.conditions))
    sidx = model.output_index(sensors)
    tau = (cycle - 1) / TAU_CYCLES  # every life starts at cycle 1
    clean_lin = linearize(model, w, theta, effects, layer, tau)
    clean = clean_lin.y[:, sidx]
    level = np.abs(clean).mean(0)
    rel = model.diagnosis.noise_rel or {}
    std = (
        np.array([rel.get(s, DEFAULT_NOISE_REL) for s in sensors])
        * level
        * cfg.noise_scale
    )
    unit = "-"
    effect_names = [e.name for e in model.effects]
    if kind in effect_names:
        effects[effect_names.index(kind)] = size
        unit = model.effects[effect_names.index(kind)].unit
    elif kind == "parameter":
        unit = model.unit_of(tgt)
    elif kind == "condition_offset":
        c = model.condition_names.index(tgt)
        size = size * 0.01 * float(np.std(w[:, c]) or 1.0)
        w_offset[c] = size
        unit = model.conditions[c].unit
    elif kind in LAYER_NAMES:
        s = list(sensors).index(tgt)
        relative = kind in ("sensor_gain", "sensor_gain_drift")
        size = size * (std[s] / level[s] if relative else std[s])
        layer[LAYER_NAMES.index(kind), sidx[s]] = size
        unit = "-" if relative else model.unit_of(tgt)
    on = np.ones(w.shape[0], bool)
    if carriers is not None:
        on = np.isin(scn.unit, np.asarray(carriers))
        bad = sorted(set(np.asarray(carriers).tolist()) - set(scn.unit.tolist()))
        if bad:
            raise ValueError(f"carriers {bad} are not units of the scenario")
        if kind == "parameter":
            theta[~on, j] = model.nominal[j]
    y = linearize(model, w, theta, effects, layer, tau, w_offset)
    x = y.y[:, sidx]
    if not on.all() and kind != "parameter":  # the other units stay clean
        x = np.where(on[:, None], x, clean)
    bump_on = ""
    if kind == "discrepancy":
        s = list(sensors).index(tgt)
        bump_on, (c_lo, c_hi), width = cfg.bump or _default_bump(model, w)
        c = model.condition_names.index(bump_on)
        c0 = rng.uniform(c_lo, c_hi)
        size = size * std[s]
        x[:, s] += on * size * np.exp(-(((w[:, c] - c0) / width) ** 2))
        unit = model.unit_of(tgt)
    noise = np.asarray(jax.random.normal(key_noise, x.shape, dtype=jnp.float64))
    x = x + std * noise
    ok = y.ok if on.all() or kind == "parameter" else np.where(on, y.ok, clean_lin.ok)
    data = Dataset(
        w=w[ok],
        x=x[ok],
        condition_names=model.condition_names,
        output_names=sensors,
        unit=scn.unit[ok],
        time=cycle[ok],
        theta=theta[ok],
        theta_names=model.parameter_names,
        source=f"synthetic:{kind}",
    )
    family = "effect" if kind in effect_names else kind
    name = {"none": "", "discrepancy": f"discrepancy[{tgt}]"}.get(
        kind, candidate_name(family, tgt)
    )
    truth = EffectTruth(
        kind, name, tgt, float(size), unit, bump_on,
        () if carriers is None else tuple(int(u) for u in carriers),
    )  # fmt: skip
    return SyntheticData(data, dict(zip(sensors, std.tolist(), strict=True)), truth)


def _default_bump(model: Model, w: np.ndarray):
    spread = w.std(0)
    c = int(np.argmax(spread > 0))
    lo, hi = np.percentile(w[:, c], [45.0, 65.0])
    return model.condition_names[c], (float(lo), float(hi)), 0.2 * float(spread[c])
