"""The verdict per unit: each added effect's size, who carries it and from when.

The fleet fit (:mod:`.fitting`) gives a constant effect one value for all units and an
undeclared parameter one trajectory per unit. A fleet where only some engines carry an
effect needs the answer per unit, from the same (final) fit:

* **Size per unit.** A parameter: its fitted trajectory ``theta_u(t) - nominal``
  with standard errors from the unit's own block of the Gauss–Newton covariance (all
  spline coefficients of that unit, the shared effects held; sigma known); the size is
  its *change over the unit's record*, last minus first cycle. A fault develops in
  service; a departure already there at the first cycle in every unit (a model's
  design mismatch, FD001's fan) is not carried by any one unit and is reported apart
  (the value at the first cycle; the ``constant_from_start`` flag). A constant effect
  (sensor layer, registered effect, condition offset): one Gauss–Newton step from the
  fleet value on that unit's rows alone, jointly with the unit's spline coefficients,
  ``b_u = b + (A_u^-1 Z_u^T r_u)_b`` with standard error ``sqrt((A_u^-1)_bb)``; the
  model is nearly linear in these effects, so the step is the unit's own estimate.
  Both standard errors are inflated by the unit's residual variance factor
  ``SSR_u / (n_u - k_u)`` when it exceeds 1 (a unit the model tracks less well gets
  wider bands rather than false carriers).
* **Carries** (the stated test): a minimum-effect z-test, ``H0: |size_u| <= delta``
  against ``|size_u| > delta`` with ``z_u = (|size_u| - delta) / std_u`` one-sided,
  ``delta`` half the effect's natural step (:func:`.effects.natural_scale`: 0.5 % of a
  turbofan health modifier, half a noise std of a sensor bias), Holm's step-down
  correction across the units at family-wise level ``alpha`` (Holm 1979). With a
  zero ``delta`` a large data set makes any departure "significant"; ``delta`` states
  what counts as an effect of consequence. Family-wise rather than false-discovery
  control because a listed unit is a claim about one engine: with probability at
  least ``1 - alpha`` no unit without an effect beyond ``delta`` is listed.
* **Onset.** A parameter: the first cycle from which its change since the first cycle
  stays beyond ``delta + z_band std(t)`` up to the unit's last cycle (``z_band`` the
  Bonferroni one-sided critical value at ``alpha / U``): the start of the persistent
  exceedance of the band; the spline is already the trajectory's smooth model, so no
  separate change-point fit is needed. A drift (additive or multiplicative): zero at the
  unit's first cycle and growing linearly, so the first cycle at which its
  accumulated change reaches one noise std of the sensor. A constant form (bias, gain,
  registered effect, offset): present from the unit's first cycle.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats as sps

from jaxcal.diagnosis.effects import Candidate, natural_scale
from jaxcal.diagnosis.fitting import FitResult, gram_stats, signature_columns
from jaxcal.diagnosis.prepare import LoopData
from jaxcal.model import Model

_RIDGE = 1e-6  # as fitting._RIDGE: keeps a unit's empty knots finite
DRIFTS = ("sensor_drift", "sensor_gain_drift")


class UnitTrajectories(NamedTuple):
    """Every per-unit parameter of a fit, per row (departure from nominal)."""

    value: dict  # name -> [N]
    std: dict  # name -> [N]
    change: dict  # name -> [N] value minus its value at the unit's first row
    change_std: dict  # name -> [N]


class UnitEffect(NamedTuple):
    """The per-unit verdict of one added effect (``U`` units)."""

    name: str
    size: np.ndarray  # [U] physical units (a parameter: change over the record)
    size_std: np.ndarray  # [U]
    p_value: np.ndarray  # [U] two-sided, uncorrected
    carries: np.ndarray  # [U] bool, Holm at alpha
    onset: np.ndarray  # [U] cycle, NaN where the unit does not carry it
    min_size: float  # delta of the test: half the effect's natural step
    trajectory: np.ndarray  # [N] the effect per row (parameter value, drift * tau, ...)
    start_value: np.ndarray  # [U] value at the unit's first cycle (parameters)
    start_std: np.ndarray  # [U]


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


def _unit_stats(model: Model, data: LoopData, fit: FitResult):
    """Gram blocks at the fit and each unit's residual variance factor (>= 1)."""
    local, glob = signature_columns(data, fit.evaluation.lin, fit.spec, model)
    stats = gram_stats(data, fit.evaluation.resid, fit.evaluation.valid, local, glob)
    ssr = np.add.reduceat(np.sum(fit.evaluation.resid**2, axis=1), data.starts[:-1])
    n_u = np.add.reduceat(fit.evaluation.valid.astype(float), data.starts[:-1])
    dof = np.maximum(n_u * data.num_sensors - stats.num_local, 1.0)
    return stats, np.maximum(ssr / dof, 1.0)


def unit_trajectories(model: Model, data: LoopData, fit: FitResult) -> UnitTrajectories:
    """``theta_u(t) - nominal`` and its pointwise std for every per-unit parameter."""
    stats, s2 = _unit_stats(model, data, fit)
    nl = stats.num_local
    a_mat = stats.gram[:, :nl, :nl] + _RIDGE * np.eye(nl)
    cov = np.linalg.inv(a_mat) * s2[:, None, None]  # [U, l, l]
    value, std, change, change_std, start = {}, {}, {}, {}, 0
    first = data.starts[:-1][data.unit]
    for name, basis in fit.spec.unit_blocks(data):
        k = basis.shape[1]
        step = natural_scale(model, name)
        coef = fit.params.unit_coef[data.unit, start : start + k]
        c_rows = cov[data.unit, start : start + k, start : start + k]
        value[name] = step * np.sum(coef * basis, axis=1)
        change[name] = value[name] - value[name][first]
        for out, b in ((std, basis), (change_std, basis - basis[first])):
            var = np.einsum("ni,nij,nj->n", b, c_rows, b)
            out[name] = step * np.sqrt(np.maximum(var, 0.0))
        start += k
    return UnitTrajectories(value, std, change, change_std)


def _constant_per_unit(stats, s2, fit: FitResult, g: int):
    """Per-unit estimate and std of the shared effect ``g`` (module docstring)."""
    nl = stats.num_local
    sel = np.concatenate([np.arange(nl), [nl + g]])
    a_mat = stats.gram[:, sel[:, None], sel[None, :]]
    a_mat = a_mat + np.diag(np.r_[np.full(nl, _RIDGE), 0.0])
    rhs = stats.score[:, sel]
    # a unit on which the effect has no signature gets NaN, not a number from noise
    with np.errstate(all="ignore"):
        step = np.linalg.solve(a_mat, rhs[:, :, None])[:, -1, 0]
        var = np.linalg.inv(a_mat)[:, -1, -1] * s2
    scale = fit.spec.global_effects[g].scale
    value = fit.global_values()[g] + scale * step
    std = scale * np.sqrt(np.where(var > 0, var, np.nan))
    return value, std


def _first_persistent(above: np.ndarray, cycle: np.ndarray) -> float:
    """First cycle from which ``above`` holds to the end (NaN if not at the end)."""
    if not above.size or not above[-1]:
        return np.nan
    below = np.flatnonzero(~above)
    return float(cycle[0 if below.size == 0 else below[-1] + 1])


def unit_effects(
    model: Model,
    data: LoopData,
    fit: FitResult,
    members: Sequence[Candidate],
    alpha: float,
    trajectories: UnitTrajectories | None = None,
) -> list[UnitEffect]:
    """The per-unit verdict of each added effect ``members`` of the final ``fit``."""
    units = data.num_units
    first, last = data.starts[:-1], data.starts[1:] - 1
    z_band = float(sps.norm.isf(alpha / max(units, 1)))
    traj = trajectories or unit_trajectories(model, data, fit)
    need_stats = any(not c.per_unit for c in members)
    stats, s2 = _unit_stats(model, data, fit) if need_stats else (None, None)
    out = []
    for cand in members:
        onset = np.full(units, np.nan)
        delta = 0.5 * cand.scale
        if cand.per_unit:
            value, std = traj.value[cand.target], traj.std[cand.target]
            change = traj.change[cand.target]
            size, size_std = change[last], traj.change_std[cand.target][last]
            row_traj = value
            start_value, start_std = value[first], std[first]
        else:
            g = [c.name for c in fit.spec.global_effects].index(cand.name)
            size, size_std = _constant_per_unit(stats, s2, fit, g)
            row_traj = size[data.unit]
            if cand.family in DRIFTS:  # a (relative, for the gain) change per tau
                row_traj = row_traj * data.tau
            start_value, start_std = np.zeros(units), np.zeros(units)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = (np.abs(size) - delta) / size_std
        p = np.where(np.isfinite(z), sps.norm.sf(z), 1.0)
        carries = holm(p, alpha)
        for u in np.flatnonzero(carries):
            sl = slice(data.starts[u], data.starts[u + 1])
            cyc = data.cycle[sl]
            if cand.per_unit:
                band = delta + z_band * traj.change_std[cand.target][sl]
                above = np.abs(traj.change[cand.target][sl]) > band
                onset[u] = _first_persistent(above, cyc)
            elif cand.family in DRIFTS:
                s = data.sensor_names.index(cand.target)
                change = np.abs(row_traj[sl])
                if cand.family == "sensor_gain_drift":
                    change = change * np.abs(data.x[sl, s])
                onset[u] = _first_persistent(change >= data.noise_std[s], cyc)
            else:
                onset[u] = float(cyc[0])
        out.append(
            UnitEffect(
                cand.name,
                size,
                size_std,
                p,
                carries,
                onset,
                delta,
                row_traj,
                start_value,
                start_std,
            )  # fmt: skip
        )
    return out


def units_json(effect: UnitEffect, unit_ids: np.ndarray) -> list[dict]:
    """``[{unit, carries, size, size_std, onset}]`` (onset null when not carried)."""
    return [
        {
            "unit": int(uid),
            "carries": bool(c),
            "size": float(s),
            "size_std": float(e) if np.isfinite(e) else None,
            "onset": float(o) if c and np.isfinite(o) else None,
        }
        for uid, c, s, e, o in zip(
            unit_ids,
            effect.carries,
            effect.size,
            effect.size_std,
            effect.onset,
            strict=True,
        )  # fmt: skip
    ]
