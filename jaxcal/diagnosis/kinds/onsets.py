"""A step's onset profiled at the fitted model, row by row.

The screen (:mod:`jaxcal.diagnosis.fitting.screen`) scans a step's onset on a grid of
rows at the
declared-only fit. Both are approximations that matter for a large step: the grid
(48 onsets per unit for a step through a model's states) misses the true row by up to
half its spacing, and the linearisation at a point far from the truth biases the
maximiser. A step one row off leaves a burst of residual at every step it makes in
the conditions, which the noise model then reads as a higher level and a stronger
colour, and the onset's interval excludes the truth.

:func:`refine_onsets` profiles the onset of each carrier at the fitted point: with
the fit's other coefficients of the unit held in the projection (Frisch–Waugh–Lovell)
and the step's own fitted contribution given back to the residual (the partial
residual), the statistic of a step from row ``o`` is ``(z_o^T P r)^2 / z_o^T P z_o``
with ``z_o`` the prewhitened signature of the step from ``o`` *at the fitted
parameters* (through the states for a model with memory). Every row within
``window`` of the current onset is scored; the maximiser is the onset and the rows
within ``chi2_1(0.95)`` of the maximum its 95 % profile-likelihood interval.

The statistic is linear in the step's size; for a large step through a model's
states, it can prefer a row next to the best one. :func:`polish_onsets` then moves
each carrier's onset a row at a time while the model itself, evaluated with the onset
moved, fits the unit's rows better (every unit at once: the units are independent).
"""

from __future__ import annotations

import numpy as np

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.fitting.joint import FitResult, columns_of, evaluate_model
from jaxcal.diagnosis.kinds.signatures import Tangent, signatures
from jaxcal.diagnosis.kinds.table import Candidate
from jaxcal.diagnosis.kinds.terms import channel_index, layout
from jaxcal.model import Model

ONSET_CI = 3.84  # chi2_1 95 % quantile: the onset's profile-likelihood interval
_RIDGE = 1e-9


def _step_columns(model, data: LoopData, fit: FitResult, cand: Candidate, starts):
    """Prewhitened signatures ``[N, S, K]`` of the step from ``starts [U, K]`` (row
    positions within each unit) at the fitted point."""
    ev = fit.evaluation
    pos = data.position
    idx = channel_index(model, cand)
    dynamic = model.is_stateful and not cand.kind.is_sensor
    num_k = starts.shape[1]
    if dynamic:  # through the states: one tangent per candidate onset
        tangents = [
            Tangent(cand.kind.channel, idx, cand.scale * (pos >= starts[data.unit, k]))
            for k in range(num_k)
        ]
        raw = signatures(model, data, ev.inputs, tangents, like=ev.sig).cols
    else:  # the step's column is the constant's, switched on from the onset
        base = Tangent(cand.kind.channel, idx, np.full(data.num_rows, cand.scale))
        col = signatures(model, data, ev.inputs, [base], like=ev.sig).cols[:, :, :1]
        raw = col * (pos[:, None] >= starts[data.unit])[:, None, :]
    return data.whiten(np.where(ev.used[:, :, None], raw, 0.0))


def refine_onsets(
    model: Model, data: LoopData, fit: FitResult, cand: Candidate, window: int
) -> tuple[Candidate, np.ndarray]:
    """The step ``cand`` (units form, a member of ``fit``) with each carrier's onset
    profiled over the rows within ``window`` of its current one (module docstring).

    Returns:
        ``(candidate with the profiled onsets, interval [U, 2] rows)``; the interval
        is ``-1`` for units that do not carry the step.
    """
    lay, ev = fit.layout, fit.evaluation
    block = next(b for b in lay.blocks if b.name == cand.key)
    own = block.columns.start
    others = [i for i in range(lay.num_local) if i != own]
    first = data.starts[:-1]
    lengths = np.diff(data.starts)
    offsets = np.arange(-window, window + 1)
    starts = np.full((data.num_units, offsets.size), np.iinfo(np.int64).max)
    for u, row in zip(cand.carriers, cand.onsets, strict=True):
        cand_rows = np.clip(row - first[u] + offsets, 1, max(lengths[u] - 1, 1))
        starts[u] = cand_rows
    z_all = _step_columns(model, data, fit, cand, starts)
    coef = fit.params.unit_coef[:, own]
    cols = columns_of(ev)
    onsets, ci = list(cand.onsets), np.full((data.num_units, 2), -1)
    for i, u in enumerate(cand.carriers):
        sl = slice(data.starts[u], data.starts[u + 1])
        # the partial residual: the step's fitted contribution given back
        r = (ev.white[sl] + coef[u] * cols[sl, :, own]).reshape(-1)
        d = cols[sl][:, :, others].reshape(-1, len(others))
        z = z_all[sl].reshape(-1, offsets.size)
        a_inv = np.linalg.pinv(d.T @ d + _RIDGE * np.eye(len(others)))
        b = d.T @ z
        mm = np.sum(z * z, 0) - np.einsum("ik,ij,jk->k", b, a_inv, b)
        ss = z.T @ r - b.T @ a_inv @ (d.T @ r)
        with np.errstate(all="ignore"):
            stat = np.where(mm > _RIDGE, ss**2 / mm, -np.inf)
        k = int(np.argmax(stat))
        rows = first[u] + starts[u]
        onsets[i] = int(rows[k])
        near = rows[stat >= stat[k] - ONSET_CI]
        ci[u] = [near.min(), near.max()]
    return cand.with_form("units", cand.carriers, onsets), ci


def _unit_ssr(model, data: LoopData, fit: FitResult, members, index, onsets):
    """``[U]`` SSR per unit at the fitted parameters with member ``index``'s onsets
    replaced by ``onsets``."""
    members = list(members)
    cand = members[index]
    members[index] = cand.with_form("units", cand.carriers, onsets)
    spec = fit.spec.with_terms(members)
    ev = evaluate_model(
        model, data, layout(model, data, spec), fit.params, columns=False
    )
    return np.add.reduceat(np.sum(ev.white**2, axis=1), data.starts[:-1])


def polish_onsets(
    model: Model, data: LoopData, fit: FitResult, members, index: int, max_moves: int
) -> Candidate:
    """Member ``index`` of ``fit`` (a per-unit step) with each carrier's onset moved
    a row at a time while the unit's SSR at the fitted parameters falls (module
    docstring)."""
    cand = members[index]
    onsets = np.asarray(cand.onsets, int)
    carriers = np.asarray(cand.carriers, int)
    lo = data.starts[carriers] + 1
    hi = data.starts[carriers + 1] - 1
    best = _unit_ssr(model, data, fit, members, index, onsets)[carriers]
    for direction in (-1, 1):
        active = np.ones(carriers.size, bool)
        for _ in range(max_moves):
            trial = np.where(active, np.clip(onsets + direction, lo, hi), onsets)
            if not np.any(trial != onsets):
                break
            ssr = _unit_ssr(model, data, fit, members, index, trial)[carriers]
            better = active & (trial != onsets) & (ssr < best)
            if not better.any():
                break
            onsets = np.where(better, trial, onsets)
            best = np.where(better, ssr, best)
            active = better
    return cand.with_form("units", cand.carriers, onsets.tolist())
