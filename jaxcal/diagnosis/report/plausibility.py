"""Plausibility flags on a diagnosis: what "identified" must not hide.

A library effect that lowers the BIC is not necessarily a physical explanation: an
effect outside the library can be mimicked by one inside it (a hot inlet taken for a
large LPC efficiency loss), and an added term can push the declared parameters the
wrong way. Each check below is a rule stated on the final fit's per-unit values
(:mod:`jaxcal.diagnosis.report.units`); a triggered one becomes a flag in the verdict.

* ``outside_bounds``: an added effect (or a per-unit parameter after the extension)
  whose value leaves the model's stated range (``Parameter.low/high`` of a parameter
  or registered effect; the sensor layer and condition offsets state none); a
  per-unit parameter by more than its band ``z_band std``.
* ``better_than_new``: a parameter with a known direction of wear
  (``DiagnosisHints.degradation_sign``) that is, at some cycle of some unit, on the
  other side of nominal by more than the band ``z_band std`` *and* by at least half a
  natural step (so that a statistically clear but physically negligible improvement on
  a large data set is not flagged).
* ``constant_from_start``: an added parameter present from the first cycle: in some
  unit its value at the first cycle is beyond the band, at least half a natural step
  (the floor of every rule here) and at least half its end value. Wear grows in
  service; a loss already there on day one is more likely an offset of another kind
  (a condition or sensor error, a design mismatch of the model) taken for wear.
* ``declared_against_sign``: a declared parameter that, after the extension,
  improves over a unit's life (last minus first value against the direction of wear,
  beyond the band of the difference and at least half a natural step) in some unit:
  the added term took more than its share of the residual and the declared parameter
  compensates (an HPC efficiency "recovering" in service). The count before the
  extension is given beside it.
* ``sensor_worse``: an output whose tracking RMSE is higher after the extension than
  before by more than its own sampling spread, ``3 / sqrt(2 n)`` relative (``n`` rows;
  the relative std of an RMSE of ``n`` Gaussian residuals is ``1 / sqrt(2 n)``), and
  at least :data:`WORSE_FRACTION`.
"""

from __future__ import annotations

import numpy as np
from scipy import stats as sps

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.kinds.table import Candidate, natural_scale
from jaxcal.diagnosis.report.units import UnitEffect, UnitTrajectories
from jaxcal.model import Model

WORSE_FRACTION = 0.01  # relative increase of a sensor's RMSE that counts as worse
FLAGS = (
    "outside_bounds",
    "better_than_new",
    "constant_from_start",
    "declared_against_sign",
    "sensor_worse",
)


def degradation_sign(model: Model, name: str) -> int:
    """+1 / -1: the direction ``name`` moves as the system wears; 0 unknown."""
    signs = model.diagnosis.degradation_sign or {}
    if name in signs:
        return int(np.sign(signs[name]))
    for p in model.parameters:
        if p.name == name:
            if p.nominal <= p.low:
                return 1
            if p.nominal >= p.high:
                return -1
    return 0


def _flag(kind, subject, detail, units=()):
    return {"flag": kind, "subject": subject, "detail": detail, "units": list(units)}


def _ids(data, mask):
    return [int(u) for u in data.unit_ids[np.flatnonzero(mask)]]


def _per_unit_any(data: LoopData, rows: np.ndarray) -> np.ndarray:
    return np.add.reduceat(rows.astype(int), data.starts[:-1]) > 0


def _improves(data, value, std, sign, z_band, floor) -> np.ndarray:
    """``[U]`` units whose parameter improves from the first to the last cycle."""
    first, last = data.starts[:-1], data.starts[1:] - 1
    change = -sign * (value[last] - value[first])
    band = z_band * np.sqrt(std[last] ** 2 + std[first] ** 2)
    return (change > band) & (change > floor)


def plausibility_flags(
    model: Model,
    data: LoopData,
    declared,
    unit_effects: list[UnitEffect],
    members: list[Candidate],
    effect_values: dict,
    after: UnitTrajectories,
    before: UnitTrajectories,
    rmse_before: np.ndarray,
    rmse_after: np.ndarray,
    alpha: float,
) -> list[dict]:
    """The triggered flags (module docstring), each ``{flag, subject, detail, units}``.

    Args:
        model, data: as in the diagnosis.
        declared: the declared parameters.
        unit_effects: the per-unit verdicts of the added effects
        (:mod:`jaxcal.diagnosis.report.units`).
        members: the added effects (their kinds say which rules apply).
        effect_values: added effect name -> its fitted value(s) (physical units:
            one for a fleet-wide term, one per carrier for a per-unit one).
        after, before: per-unit parameter trajectories of the final and the
            declared-only fit.
        rmse_before, rmse_after: ``[S]`` tracking RMSE per output.
        alpha: level of the band (``z_band`` at ``alpha / U``, two-sided).
    """
    z_band = float(sps.norm.isf(alpha / (2.0 * max(data.num_units, 1))))
    bounds = {p.name: p for p in (*model.parameters, *model.effects)}
    flags = []
    for name, value in after.value.items():  # per-unit parameters (theta - nominal)
        flags += _parameter_flags(
            model, data, name, value, declared, after, before, bounds[name], z_band
        )
    flags += _constant_from_start_flags(model, data, unit_effects, members, z_band)
    flags += _effect_bound_flags(members, effect_values, bounds)
    flags += _sensor_worse_flags(data, rmse_before, rmse_after)
    return flags


def _parameter_flags(model, data, name, value, declared, after, before, p, z_band):
    """``outside_bounds``, ``better_than_new`` and ``declared_against_sign`` of one
    per-unit parameter (``value`` = theta - nominal, ``[N]``)."""
    flags = []
    theta = p.nominal + value
    band = z_band * after.std[name]  # a value at a bound within noise is fine
    out = _per_unit_any(data, (theta < p.low - band) | (theta > p.high + band))
    if out.any():
        worst = value[np.argmax(np.abs(value))]
        flags.append(_flag(
            "outside_bounds", name,
            f"{name} leaves its range [{p.low:g}, {p.high:g}] in {out.sum()} "
            f"unit(s) (departure up to {worst:+.4g})", _ids(data, out),
        ))  # fmt: skip
    sign = degradation_sign(model, name)
    if sign == 0:
        return flags
    floor = 0.5 * natural_scale(model, name)
    wrong = -sign * value
    rows = (wrong > z_band * after.std[name]) & (wrong > floor)
    bad = _per_unit_any(data, rows)
    if bad.any():
        flags.append(_flag(
            "better_than_new", name,
            f"{name} is better than new (the wrong side of nominal by up to "
            f"{-sign * wrong.max():+.4g}, beyond its band) in {bad.sum()} of "
            f"{data.num_units} units", _ids(data, bad),
        ))  # fmt: skip
    if name in declared and name in before.value:
        moved = _improves(data, value, after.std[name], sign, z_band, floor)
        was = _improves(data, before.value[name], before.std[name], sign, z_band, floor)
        if moved.any():
            flags.append(_flag(
                "declared_against_sign", name,
                f"after the extension the declared {name} improves over the "
                f"unit's life (against its direction of wear) in {moved.sum()} "
                f"of {data.num_units} units (before the extension: {was.sum()})",
                _ids(data, moved),
            ))  # fmt: skip
    return flags


def _constant_from_start_flags(model, data, unit_effects, members, z_band) -> list:
    """``constant_from_start`` of the added effects whose kind has the rule."""
    flags = []
    by_name = {c.name: c for c in members}
    for eff in unit_effects:
        target, cand = eff.name, by_name[eff.name]
        if "constant_from_start" not in cand.kind.rules:
            continue
        step = natural_scale(model, cand.target)
        start, end = eff.start_value, eff.start_value + eff.size
        const = (
            (np.abs(start) > z_band * eff.start_std)
            & (np.abs(start) >= 0.5 * step)
            & (np.abs(start) >= 0.5 * np.abs(end))
        )
        if const.any():
            flags.append(_flag(
                "constant_from_start", target,
                f"{target} is already {np.median(start[const]):+.4g} (median) at "
                f"the first cycle in {const.sum()} of {data.num_units} units: a "
                "departure present from day one, not wear",
                _ids(data, const),
            ))  # fmt: skip
    return flags


def _effect_bound_flags(members, effect_values: dict, bounds: dict) -> list:
    """``outside_bounds`` of the added registered effects (their stated range)."""
    flags = []
    for cand in members:
        if cand.kind.channel != "effect" or cand.target not in bounds:
            continue
        p = bounds[cand.target]
        values = np.atleast_1d(effect_values[cand.name])
        bad = values[(values < p.low) | (values > p.high)]
        if bad.size:
            flags.append(_flag(
                "outside_bounds", cand.name,
                f"{cand.name} = {bad[np.argmax(np.abs(bad))]:.4g} lies outside its "
                f"range [{p.low:g}, {p.high:g}]",
            ))  # fmt: skip
    return flags


def _sensor_worse_flags(data, rmse_before, rmse_after) -> list:
    """``sensor_worse``: RMSE up by more than its sampling spread (and at least
    :data:`WORSE_FRACTION`)."""
    margin = max(WORSE_FRACTION, 3.0 / np.sqrt(2.0 * max(data.num_rows, 1)))
    worse = rmse_after > rmse_before * (1.0 + margin)
    return [
        _flag(
            "sensor_worse", data.sensor_names[s],
            f"{data.sensor_names[s]} tracks worse after the extension: RMSE "
            f"{rmse_before[s]:.4g} -> {rmse_after[s]:.4g}",
        )
        for s in np.flatnonzero(worse)
    ]  # fmt: skip
