"""Test data sets with exactly one undeclared effect of a chosen kind, for any model.

A *scenario* supplies the clean rows: conditions, all parameters (the declared ones
drifting with a per-row health index), unit and cycle (e.g.
:func:`jaxcal.models.turbofan.scenario.make_scenario` flies N-CMAPSS-like lives). This
module switches one effect on in the extended model of
:mod:`jaxcal.diagnosis.kinds.signatures` (:func:`apply_effect`, :func:`add_bump`), on
every unit or only on some (``carriers``), adds Gaussian noise at the model's reference
relative level per output (``DiagnosisHints.noise_rel``, times ``noise_scale``), white
or AR(1)-coloured along each unit's rows (``noise_ar``), and returns a
:class:`~jaxcal.data.dataset.Dataset` with the truth. A model with memory is simulated
unit by unit from its initial state, the effect acting through the states.

Effect kinds (:func:`kinds`; how each enters the model and is sized comes from the
table of :mod:`jaxcal.diagnosis.kinds.table`), drawn from ``SyntheticConfig.sizes``
(magnitude uniform in the range, sign as noted; defaults :func:`default_sizes`):

* ``none``: the clean data (false-alarm runs);
* ``parameter``: an undeclared parameter drifting from nominal with the unit's health
  index to an end value in the range; ``parameter_step``: the same parameter jumping
  at an onset (sudden damage);
* each registered effect of the model (``model.effects``), constant over the data;
* ``sensor_bias`` / ``sensor_gain`` / ``sensor_drift`` / ``sensor_gain_drift`` /
  ``sensor_step`` on a random output, sized in multiples of its noise std (a gain
  relative to the output's mean level, a drift per 100 cycles since the unit's first
  cycle, a step from an onset);
* ``discrepancy``: an effect outside the library, a smooth bump in one condition added
  to one output, ``A sigma exp(-((w_c - c0) / width)^2)`` (``SyntheticConfig.bump``);
* ``condition_offset`` (only if the model allows condition offsets): a logged
  condition off by a constant, in % of the condition's spread.

A step's onset is drawn per carrying unit uniformly in ``onset_range`` of its life.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.diagnosis.data.prepare import reference_noise_rel
from jaxcal.diagnosis.data.synthetic_effects import add_bump, apply_effect, kind_of
from jaxcal.diagnosis.kinds.signatures import signatures, zero_inputs
from jaxcal.diagnosis.kinds.table import (
    KINDS,
    TAU_CYCLES,
    natural_scale,
    offset_conditions,
)
from jaxcal.model import Model
from jaxcal.typedefs import PRNGKey

_SENSOR_KINDS = ("sensor_bias", "sensor_gain", "sensor_drift")


def kinds(model: Model) -> tuple[str, ...]:
    """The effect kinds a synthetic data set of ``model`` can hold (module doc)."""
    extra = ("condition_offset",) if offset_conditions(model) else ()
    effects = () if model.is_stateful else tuple(e.name for e in model.effects)
    # later additions go last, so that the position of the older kinds (which seeds
    # the study's records) does not move
    return (
        "none", "parameter", *effects, *_SENSOR_KINDS, "discrepancy",
        "sensor_gain_drift", *extra, "parameter_step", "sensor_step",
    )  # fmt: skip


def default_sizes(model: Model) -> dict[str, tuple[tuple[float, float], int]]:
    """kind -> ((low, high) magnitude, sign); sign +1, -1 or 0 (random).

    From the kinds table (:mod:`jaxcal.diagnosis.kinds.table`: natural steps, noise std,
    noise std relative to the level, % of a condition's spread); registered effects in
    their own units (0.5 to 2 natural steps); the discrepancy bump 3 to 6 noise std.
    """
    out = {}
    for label in kinds(model)[1:]:
        if label == "discrepancy":
            out[label] = ((3.0, 6.0), 0)
            continue
        kind = kind_of(model, label)
        lo, hi = kind.size_range
        if kind.channel == "effect":
            step = natural_scale(model, label)
            lo, hi = lo * step, hi * step
        out[label] = ((lo, hi), 0)
    return out


class Scenario(NamedTuple):
    """Clean rows of a synthetic data set (``N`` rows, sorted by unit then cycle)."""

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
        noise_ar: AR(1) coefficient of the noise along each unit's rows (0: white;
            the marginal std is kept).
        sizes: kind -> ((low, high), sign) (default :func:`default_sizes`); the
            units of ``parameter`` are the parameter's own when ``parameter_physical``.
        parameter_physical: ``sizes["parameter"]`` is in the parameter's units
            (True) or in natural steps (False).
        bump: ``(condition, (c0_low, c0_high), width)`` of the discrepancy bump
            (default: the first condition that varies, centre between its 45th and
            65th percentile, width 20 % of its spread).
        onset_range: a step's onset, as a share of the carrier's life.
    """

    sensors: tuple[str, ...] = ()
    declared: tuple[str, ...] = ()
    noise_scale: float = 1.0
    noise_ar: float = 0.0
    sizes: Mapping[str, Any] | None = None
    parameter_physical: bool = False
    bump: tuple[str, tuple[float, float], float] | None = None
    onset_range: tuple[float, float] = (0.3, 0.7)

    def __post_init__(self):
        if not self.noise_scale > 0 or not 0 <= self.noise_ar < 1:
            raise ValueError("SyntheticConfig: noise_scale > 0, 0 <= noise_ar < 1")


class EffectTruth(NamedTuple):
    """The effect put into a data set."""

    kind: str  # one of kinds(model)
    name: str  # the library candidate's name ("" for none, "discrepancy[<s>]")
    target: str  # output, parameter, effect or condition ("" for none)
    size: float  # physical units (the model's)
    unit: str
    condition: str = ""  # the bump's condition (discrepancy only)
    carriers: tuple[int, ...] = ()  # unit ids that carry it (empty: every unit)
    onsets: tuple[float, ...] = ()  # a step's onset cycle per carrier


class SyntheticData(NamedTuple):
    """A generated data set, the noise it got and the effect it contains."""

    data: Dataset
    noise_std: dict  # output -> marginal std used for the noise
    truth: EffectTruth


class _Rows(NamedTuple):
    """The minimum :func:`~jaxcal.diagnosis.kinds.signatures.signatures` needs of a
    data set."""

    w: np.ndarray
    sensor_idx: np.ndarray
    starts: np.ndarray
    num_units: int
    num_rows: int


def rows_of(w: np.ndarray, unit: np.ndarray, sensor_idx) -> _Rows:
    """Rows sorted by unit for the signatures (``unit`` must be sorted)."""
    if np.any(np.diff(unit) < 0):
        raise ValueError("rows must be sorted by unit")
    _, first = np.unique(unit, return_index=True)
    return _Rows(w, np.asarray(sensor_idx), np.append(first, unit.size),
                 first.size, unit.size)  # fmt: skip


def ar1_noise(rng: np.random.Generator, shape, unit: np.ndarray, phi: float):
    """Unit-variance noise ``[N, S]``, AR(1) with coefficient ``phi`` along each
    unit's rows (stationary from each unit's first row)."""
    eps = rng.standard_normal(shape)
    if phi == 0:
        return eps
    out = eps.copy()
    new = np.r_[True, unit[1:] != unit[:-1]]
    scale = np.sqrt(1.0 - phi**2)
    for t in range(1, shape[0]):
        if not new[t]:
            out[t] = phi * out[t - 1] + scale * eps[t]
    return out


def _targets(model: Model, label: str, sensors, declared) -> tuple[str, ...]:
    """What an effect of study label ``label`` can act on (a registered effect: on
    itself; the discrepancy bump: an output)."""
    if label == "discrepancy":
        return tuple(sensors)
    if label not in KINDS:
        return (label,)
    return KINDS[label].targets(model, sensors, declared)


def _pick(rng, kind, sensors, declared, model, sizes) -> tuple[str, float]:
    (lo, hi), sign = sizes[kind]
    size = rng.uniform(lo, hi) * (sign if sign else rng.choice([-1.0, 1.0]))
    return str(rng.choice(list(_targets(model, kind, sensors, declared)))), float(size)


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
        model: the model (float64 enabled by the caller).
        kind: one of :func:`kinds`.
        cfg: static settings.
        scenario: ``scenario(keys [4]) -> Scenario`` (the clean rows).
        target: force the output / parameter / condition the effect acts on.
        size: force the size, in the units of ``cfg.sizes`` (default: drawn).
        carriers: unit ids that carry the effect (default every unit): a fleet in
            which only some units have it; the others get the clean rows.

    Returns:
        :class:`SyntheticData`; rows where the model is invalid are left out.
    """
    sensors = tuple(cfg.sensors) or model.output_names
    _check_request(model, kind, target, sensors, cfg.declared)
    sizes = {**default_sizes(model), **dict(cfg.sizes or {})}
    keys = jax.random.split(key, 6)
    rng = np.random.default_rng(np.asarray(jax.random.key_data(keys[4])).ravel())
    tgt, size_drawn = (
        ("", 0.0) if kind == "none"
        else _pick(rng, kind, sensors, cfg.declared, model, sizes)
    )  # fmt: skip
    tgt = target or tgt
    size = size if size is not None else size_drawn
    scn = scenario(keys[:4])
    order = np.lexsort((scn.cycle, scn.unit))
    w, unit, cycle = scn.w[order], scn.unit[order], scn.cycle[order]
    theta, health = np.array(scn.theta, np.float64)[order], scn.health[order]
    rows = rows_of(w, unit, model.output_index(sensors))
    inputs = zero_inputs(model, w.shape[0], rows.num_units)._replace(theta=theta)
    level = np.abs(signatures(model, rows, inputs).x).mean(0)
    std = reference_noise_rel(model, sensors) * level * cfg.noise_scale
    on = _carrier_rows(unit, carriers)
    ids = np.unique(unit[on]) if kind != "none" else np.zeros(0)
    onsets = _step_onsets(rng, kind, ids, unit, cycle, cfg.onset_range)
    step_on = np.array([cycle[i] >= onsets.get(int(unit[i]), np.inf)
                        for i in range(w.shape[0])])  # fmt: skip
    tau = (cycle - 1) / TAU_CYCLES  # every life starts at cycle 1
    size, unit_str = apply_effect(model, kind, tgt, size, cfg.parameter_physical,
                                  inputs, on, step_on, tau, health, std, level,
                                  sensors, w)  # fmt: skip
    sig = signatures(model, rows, inputs)
    x = sig.y.copy()
    bump_on = ""
    if kind == "discrepancy":
        s = list(sensors).index(tgt)
        bump_on, size = add_bump(rng, model, cfg.bump, x[:, s], size * std[s], w, on)
        unit_str = model.unit_of(tgt)
    noise_rng = np.random.default_rng(np.asarray(jax.random.key_data(keys[5])).ravel())
    x = x + std * ar1_noise(noise_rng, x.shape, unit, cfg.noise_ar)
    ok = sig.ok
    data = Dataset(
        w=w[ok], x=x[ok], condition_names=model.condition_names, output_names=sensors,
        unit=unit[ok], time=cycle[ok], theta=inputs.theta[ok],
        theta_names=model.parameter_names, source=f"synthetic:{kind}",
    )  # fmt: skip
    truth = EffectTruth(
        kind, _truth_name(model, kind, tgt), tgt, float(size), unit_str, bump_on,
        () if carriers is None else tuple(int(u) for u in carriers),
        tuple(onsets[int(u)] for u in ids) if onsets else (),
    )  # fmt: skip
    return SyntheticData(data, dict(zip(sensors, std.tolist(), strict=True)), truth)


def _check_request(model: Model, kind: str, target, sensors, declared) -> None:
    """``kind`` must be one of :func:`kinds`, a forced ``target`` one it can act on."""
    valid_kinds = kinds(model)
    if kind not in valid_kinds:
        raise ValueError(
            f"unknown effect kind {kind!r}; valid: {', '.join(valid_kinds)}"
        )
    if kind != "none" and target is not None:
        valid_targets = _targets(model, kind, sensors, declared)
        if target not in valid_targets:
            raise ValueError(
                f"target={target!r} is not valid for kind {kind!r}; valid: "
                f"{list(valid_targets)}"
            )


def _carrier_rows(unit: np.ndarray, carriers) -> np.ndarray:
    """``[N]`` bool: the rows of the carrying units (every row when ``None``)."""
    if carriers is None:
        return np.ones(unit.shape[0], bool)
    bad = sorted(set(np.asarray(carriers).tolist()) - set(unit.tolist()))
    if bad:
        raise ValueError(f"carriers {bad} are not units of the scenario")
    return np.isin(unit, np.asarray(carriers))


def _step_onsets(rng, kind, ids, unit, cycle, onset_range) -> dict[int, float]:
    """unit id -> a step's onset cycle, drawn uniformly in ``onset_range`` of the
    unit's life (one draw per carrier, in ``ids`` order); none unless ``kind`` is a
    step."""
    onsets = {}
    if kind not in KINDS or KINDS[kind].profile != "step":
        return onsets
    for u in ids:
        cyc = cycle[unit == u]
        share = rng.uniform(*onset_range)
        onsets[int(u)] = float(cyc[int(round(share * (cyc.size - 1)))])
    return onsets


def _truth_name(model: Model, kind: str, tgt: str) -> str:
    """The library candidate's name of the effect put in ("" for none)."""
    if kind in ("none", "discrepancy"):
        return "" if kind == "none" else f"discrepancy[{tgt}]"
    return kind_of(model, kind).candidate_name(tgt)
