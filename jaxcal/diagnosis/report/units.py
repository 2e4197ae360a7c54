"""The verdict per unit: each added effect's size, who carries it and from when.

From the final fit (:mod:`jaxcal.diagnosis.fitting.joint`, prewhitened residual):

* **Size per unit.** A parameter that changes smoothly: its fitted trajectory
  ``theta_u(t) - nominal`` with standard errors from the unit's own block of the
  Gauss–Newton covariance (all its local coefficients, the shared terms held); the
  size is its *change over the unit's record*, last minus first cycle (a departure
  already there at the first cycle in every unit, a design mismatch, is reported apart:
  the value at the first cycle, the ``constant_from_start`` flag). Any other term
  (constant, drift, step): one Gauss–Newton step from its fitted value on that unit's
  rows alone, jointly with the unit's local coefficients, with standard error
  ``sqrt((A_u^-1)_bb)``; the model is nearly linear in these effects, so the step is
  the unit's own estimate (a step's, at its own onset; a unit without an onset has
  none). Standard errors are inflated by the unit's residual variance factor
  ``SSR_u / (n_u - k_u)`` when it exceeds 1.
* **Carries**: a unit the form allows (every unit for a fleet-wide term; the carriers
  the screen chose for a per-unit one, each on its own data) whose effect passes the
  minimum-effect z-test ``H0: |size_u| <= delta`` against ``|size_u| > delta``,
  ``z_u = (|size_u| - delta) / std_u`` one-sided, ``delta`` the kind's minimum effect
  in natural steps (:class:`jaxcal.diagnosis.kinds.table.EffectKind` ``min_effect``),
  with Holm's step-down
  correction across the units at family-wise level ``alpha`` (Holm 1979). A listed
  unit is a claim about one engine: with probability at least ``1 - alpha`` no unit
  without an effect beyond ``delta`` is listed, and no unit whose own data do not
  show the effect is.
* **Onset.** A step: the scanned onset and its 95 % profile-likelihood interval
  (:mod:`jaxcal.diagnosis.fitting.screen`). A smooth parameter: the first cycle from
  which its change since
  the first cycle stays beyond ``delta + z_band std(t)`` up to the unit's last cycle
  (``z_band`` the Bonferroni one-sided critical value at ``alpha / U``). A drift: the
  first cycle at which its accumulated change reaches one noise std of the sensor. A
  constant form: the unit's first cycle.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats as sps

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.fitting.joint import RIDGE, FitResult, columns_of, gram_stats
from jaxcal.diagnosis.kinds.signatures import Tangent, signatures
from jaxcal.diagnosis.kinds.table import Candidate
from jaxcal.diagnosis.kinds.terms import term_profile
from jaxcal.model import Model


class UnitTrajectories(NamedTuple):
    """Every per-unit parameter of a fit, per row (departure from nominal)."""

    value: dict  # name -> [N]
    std: dict  # name -> [N]
    change: dict  # name -> [N] value minus its value at the unit's first row
    change_std: dict  # name -> [N]


class UnitEffect(NamedTuple):
    """The per-unit verdict of one added effect (``U`` units)."""

    name: str  # the effect's name
    form: str  # fleet or units
    size: np.ndarray  # [U] physical units (a smooth parameter: change over the record)
    size_std: np.ndarray  # [U]
    p_value: np.ndarray  # [U] one-sided minimum-effect, uncorrected (1: not allowed)
    carries: np.ndarray  # [U] bool, Holm at alpha
    onset: np.ndarray  # [U] cycle, NaN where the unit does not carry it
    onset_ci: np.ndarray  # [U, 2] cycles of a step's onset interval (else NaN)
    min_size: float  # delta of the test: the kind's min_effect natural steps
    trajectory: np.ndarray  # [N] the effect per row (parameter value, drift * tau, ...)
    start_value: np.ndarray  # [U] value at the unit's first cycle (parameters)
    start_std: np.ndarray  # [U]
    min_effect: float = 0.1  # delta in natural steps (EffectKind.min_effect)


def holm(p: np.ndarray, alpha: float) -> np.ndarray:
    """Holm's step-down rejections ``[m]`` bool at family-wise level ``alpha``."""
    p = np.asarray(p, np.float64)
    order = np.argsort(p)
    m = p.size
    reject = np.zeros(m, bool)
    for rank, i in enumerate(order):
        if not p[i] <= alpha / (m - rank):
            break
        reject[i] = True
    return reject


def _unit_stats(data: LoopData, fit: FitResult, cols=None):
    """Gram blocks at the fit (of ``cols`` when given) and each unit's residual
    variance factor (>= 1)."""
    ev = fit.evaluation
    cols = columns_of(ev) if cols is None else cols
    stats = gram_stats(data, ev.white, cols, fit.layout.num_local)
    ssr = np.add.reduceat(np.sum(ev.white**2, axis=1), data.starts[:-1])
    n_u = np.add.reduceat(ev.used.sum(1).astype(float), data.starts[:-1])
    dof = np.maximum(n_u - fit.layout.num_local, 1.0)
    return stats, np.maximum(ssr / dof, 1.0)


def unit_trajectories(model: Model, data: LoopData, fit: FitResult) -> UnitTrajectories:
    """``theta_u(t) - nominal`` and its pointwise std for every per-unit parameter."""
    stats, s2 = _unit_stats(data, fit)
    nl = fit.layout.num_local
    a_mat = stats.gram[:, :nl, :nl] + RIDGE * np.eye(nl)
    cov = np.linalg.inv(a_mat) * s2[:, None, None]  # [U, l, l]
    first = data.starts[:-1][data.unit]
    value, std, change, change_std = {}, {}, {}, {}
    for name in fit.spec.unit_params:
        j = model.parameter_names.index(name)
        cols = [c for c, t in enumerate(fit.layout.tangents[:nl])
                if t.channel == "parameter" and t.index == j]  # fmt: skip
        prof = np.stack([fit.layout.tangents[c].profile for c in cols], axis=1)
        coef = fit.params.unit_coef[data.unit][:, cols]
        c_rows = cov[data.unit][:, cols][:, :, cols]
        value[name] = np.sum(coef * prof, axis=1)
        change[name] = value[name] - value[name][first]
        for out, b in ((std, prof), (change_std, prof - prof[first])):
            var = np.einsum("ni,nij,nj->n", b, c_rows, b)
            out[name] = np.sqrt(np.maximum(var, 0.0))
    return UnitTrajectories(value, std, change, change_std)


def _everywhere(cand: Candidate, num_units: int) -> Candidate:
    """The term on every unit (a step keeps its carriers: only they have an onset)."""
    if not cand.per_unit or cand.kind.profile == "step":
        return cand
    return cand.with_form("units", range(num_units))


def _term_per_unit(model, data, fit: FitResult, cand: Candidate, s2):
    """Per-unit estimate and std of a non-spline term (module docstring)."""
    nl = fit.layout.num_local
    block = next(b for b in fit.layout.blocks if b.name == cand.key)
    tan = fit.layout.tangents[(0 if block.local else nl) + block.columns.start]
    prof = term_profile(data, _everywhere(cand, data.num_units))[:, 0]
    ev = fit.evaluation
    sig = signatures(model, data, ev.inputs, [Tangent(tan.channel, tan.index, prof)],
                     like=ev.sig)  # fmt: skip
    col = data.whiten(np.where(ev.used[:, :, None], sig.cols, 0.0))
    others = np.ones(nl, bool)  # the unit's local columns but the term's own
    if block.local:
        others[block.columns] = False
    cols = np.concatenate([columns_of(ev)[:, :, :nl][:, :, others], col], axis=2)
    k = int(others.sum())
    st = gram_stats(data, ev.white, cols, k + 1)
    # a unit on which the term has no signature (a step's non-carrier) gets a tiny
    # ridge, and NaN below, not a number from noise
    a_mat = st.gram + np.diag(np.r_[np.full(k, RIDGE), 1e-12])
    with np.errstate(all="ignore"):
        step = np.linalg.solve(a_mat, st.score[:, :, None])[:, -1, 0]
        var = np.linalg.inv(a_mat)[:, -1, -1] * s2
    values = fit.term_values(cand)
    current = values[:, 0] if block.local else np.full(data.num_units, values[0])
    value = current + cand.scale * step
    std = cand.scale * np.sqrt(np.where(var > 0, var, np.nan))
    if cand.kind.profile == "step":  # a unit without an onset has no step size
        off = np.ones(data.num_units, bool)
        off[list(cand.carriers)] = False
        value[off], std[off] = np.nan, np.nan
    return value, std


def _spline_per_unit(model, data, fit: FitResult, cand: Candidate, s2):
    """``(change over the record, std)`` per unit of a smoothly changing parameter
    fitted in some units, for the others: one Gauss–Newton step of its spline
    coefficients on each unit's rows alone (NaN where it was fitted)."""
    nl = fit.layout.num_local
    block = next(b for b in fit.layout.blocks if b.name == cand.key)
    tan = fit.layout.tangents[block.columns.start]
    prof = term_profile(data, cand.with_form("units", range(data.num_units)))
    ev = fit.evaluation
    tangents = [Tangent(tan.channel, tan.index, p) for p in prof.T]
    sig = signatures(model, data, ev.inputs, tangents, like=ev.sig)
    cols = data.whiten(np.where(ev.used[:, :, None], sig.cols, 0.0))
    others = np.ones(nl, bool)
    others[block.columns] = False
    k = prof.shape[1]
    z = np.concatenate([columns_of(ev)[:, :, :nl][:, :, others], cols], axis=2)
    st = gram_stats(data, ev.white, z, z.shape[2])
    a_mat = st.gram + RIDGE * np.eye(z.shape[2])
    step = np.linalg.solve(a_mat, st.score[:, :, None])[:, -k:, 0]
    cov = np.linalg.inv(a_mat)[:, -k:, -k:] * s2[:, None, None]
    first, last = data.starts[:-1], data.starts[1:] - 1
    d = prof[last] - prof[first]  # [U, k]: change of each coefficient's profile
    size = np.einsum("uk,uk->u", d, step)
    std = np.sqrt(np.maximum(np.einsum("uk,ukj,uj->u", d, cov, d), 0.0))
    fitted = np.zeros(data.num_units, bool)
    fitted[list(cand.carriers)] = True
    return np.where(fitted, np.nan, size), np.where(fitted, np.nan, std)


def _first_persistent(above: np.ndarray, cycle: np.ndarray) -> float:
    """First cycle from which ``above`` holds to the end (NaN if not at the end)."""
    if not above.size or not above[-1]:
        return np.nan
    below = np.flatnonzero(~above)
    return float(cycle[0 if below.size == 0 else below[-1] + 1])


def _carrier_onsets(data, cand, carries, traj, row_traj, delta, z_band, onset_ci):
    """``(onset [U], onset interval [U, 2])`` in cycles of each carrier (NaN
    elsewhere): where a spline's change or a drift's accumulated change first stays
    beyond its band, a step's fitted onset (and its profiled interval when known),
    the first cycle for a constant."""
    onset = np.full(data.num_units, np.nan)
    ci = np.full((data.num_units, 2), np.nan)
    spline = cand.kind.channel == "parameter" and cand.kind.profile == "spline"
    for u in np.flatnonzero(carries):
        sl = slice(data.starts[u], data.starts[u + 1])
        cyc = data.cycle[sl]
        if spline:
            band = delta + z_band * traj.change_std[cand.target][sl]
            above = np.abs(traj.change[cand.target][sl]) > band
            onset[u] = _first_persistent(above, cyc)
        elif cand.kind.profile == "step":
            row = cand.onsets[list(cand.carriers).index(u)]
            onset[u] = data.cycle[row]
            if onset_ci and cand.name in onset_ci:
                ci[u] = data.cycle[np.asarray(onset_ci[cand.name][u], int)]
        elif cand.kind.profile == "drift":
            s = data.sensor_names.index(cand.target)
            change = np.abs(row_traj[sl])
            if cand.kind.channel == "multiplicative":
                change = change * np.abs(data.x[sl, s])
            onset[u] = _first_persistent(change >= data.noise_std[s], cyc)
        else:
            onset[u] = float(cyc[0])
    return onset, ci


def unit_effects(
    model: Model,
    data: LoopData,
    fit: FitResult,
    members: Sequence[Candidate],
    alpha: float,
    trajectories: UnitTrajectories | None = None,
    onset_ci: dict | None = None,
) -> list[UnitEffect]:
    """The per-unit verdict of each added effect ``members`` of the final ``fit``."""
    units = data.num_units
    first, last = data.starts[:-1], data.starts[1:] - 1
    z_band = float(sps.norm.isf(alpha / max(units, 1)))
    traj = trajectories or unit_trajectories(model, data, fit)
    _, s2 = _unit_stats(data, fit)
    out = []
    for cand in members:
        delta = cand.kind.min_effect * cand.scale
        spline = cand.kind.channel == "parameter" and cand.kind.profile == "spline"
        if spline:
            value, std = traj.value[cand.target], traj.std[cand.target]
            change = traj.change[cand.target]
            size, size_std = change[last], traj.change_std[cand.target][last]
            if cand.per_unit and len(cand.carriers) < units:  # the others' own
                own, own_std = _spline_per_unit(model, data, fit, cand, s2)
                size = np.where(np.isnan(own), size, own)
                size_std = np.where(np.isnan(own_std), size_std, own_std)
            row_traj = value
            start_value, start_std = value[first], std[first]
        allowed = np.ones(units, bool)
        if cand.per_unit:
            allowed[:] = False
            allowed[list(cand.carriers)] = True
        if not spline:
            size, size_std = _term_per_unit(model, data, fit, cand, s2)
            shape = term_profile(data, _everywhere(cand, units))[:, 0] / cand.scale
            fitted = np.where(allowed, np.nan_to_num(size), 0.0)
            row_traj = fitted[data.unit] * shape
            start_value, start_std = np.zeros(units), np.zeros(units)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = (np.abs(size) - delta) / size_std
        p = np.where(np.isfinite(z) & allowed, sps.norm.sf(z), 1.0)
        carries = holm(p, alpha) & allowed
        onset, ci = _carrier_onsets(
            data, cand, carries, traj, row_traj, delta, z_band, onset_ci
        )
        out.append(UnitEffect(
            cand.name, cand.form, size, size_std, p, carries, onset, ci, delta,
            row_traj, start_value, start_std, cand.kind.min_effect,
        ))  # fmt: skip
    return out


def units_json(effect: UnitEffect, unit_ids: np.ndarray) -> list[dict]:
    """``[{unit, carries, size, size_std, onset, onset_ci}]`` (onset null when not
    carried)."""

    def num(v):
        return float(v) if np.isfinite(v) else None

    return [
        {
            "unit": int(uid),
            "carries": bool(c),
            "size": num(s),
            "size_std": num(e),
            "onset": num(o) if c else None,
            "onset_ci": [num(v) for v in ci] if c and np.all(np.isfinite(ci)) else None,
        }
        for uid, c, s, e, o, ci in zip(
            unit_ids,
            effect.carries,
            effect.size,
            effect.size_std,
            effect.onset,
            effect.onset_ci,
            strict=True,
        )  # fmt: skip
    ]


def fleet_summary(eff, entry: dict) -> dict:
    """Fleet numbers of one effect from the same final fit as its per-unit values.

    A per-unit smooth parameter's fleet size is the mean over units of its change
    over each record (the per-unit size), beside the mean values at the first and the
    last cycle; its standard error is that of the mean, at least the units' own mean
    standard error. Carriers and the rest are summarised apart, since a fleet mean
    blends them.
    """
    out = {"carriers": int(eff.carries.sum())}
    if entry["family"] == "parameter":
        size = eff.size
        u = size.size
        spread = float(np.var(size, ddof=1)) / u if u > 1 else 0.0
        own = float(np.mean(eff.size_std**2)) / u
        out["size"] = float(np.mean(size))
        out["std"] = float(np.sqrt(max(spread, own)))
        out["start_value"] = float(np.mean(eff.start_value))
        out["end_value"] = float(np.mean(eff.start_value + size))
    for key, mask in (("size_carriers", eff.carries), ("size_others", ~eff.carries)):
        vals = eff.size[mask]
        vals = vals[np.isfinite(vals)]
        out[key] = float(np.mean(vals)) if vals.size else None
    return out
