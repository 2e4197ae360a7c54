"""Linearised screening of candidate effects, in every form, at the declared-only fit.

At the declared-only fit (the "null"), the prewhitened residual ``r`` and the
prewhitened signatures ``D`` of the declared coefficients are known per unit. Adding
columns ``Z`` to that linear model lowers the SSR by the score statistic of Rao (1948)
in Gauss–Newton form, ``LR = s^T M^-1 s`` with ``s = Z^T P r``, ``M = Z^T P Z`` and
``P`` the projection off ``D`` (Frisch–Waugh–Lovell), computed unit by unit. Because
the declared coefficients are per unit, a per-unit effect's statistic is a sum of
independent per-unit terms ``LR_u``, so every form is scored without a model
evaluation:

* **fleet** form (one value shared by all units): ``LR = (sum_u s_u)^2 / sum_u M_u``;
* **units** form: the carriers are the units with the largest ``LR_u``, as many as
  maximise ``sum_{u in C} LR_u - |C| k ln n - 2 ln C(U, |C|)`` (BIC with the extended
  BIC's price of choosing the subset, Chen & Chen 2008): an effect carried by a
  minority of units is fitted where it is, and not diluted fleet-wide;
* **steps** (a sensor step, a parameter step): each unit's ``LR_u(t0)`` is scanned over
  a grid of onsets (the columns are the step's signature from ``t0`` on, whitened); the
  unit's estimate is the maximiser and its 95 % interval the onsets whose profile
  statistic is within ``chi2_1(0.95) = 3.84`` of the maximum (a profile-likelihood
  interval); the onset counts as a parameter.

The same projected blocks give each candidate's *detectability* (the share of its
signature's norm left after projecting out the declared parameters' signatures) and
the *overlap* of two candidates (the share of one's fitted signal the other's columns
reproduce), used to flag confounding.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy.special import gammaln

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.fitting.joint import (
    FitResult,
    GramStats,
    columns_of,
    schur_solve,
)
from jaxcal.diagnosis.kinds.onsets import ONSET_CI
from jaxcal.diagnosis.kinds.signatures import Tangent, signatures
from jaxcal.diagnosis.kinds.table import Candidate
from jaxcal.diagnosis.kinds.terms import (
    ModelParams,
    ModelSpec,
    channel_index,
    layout,
    term_profile,
)
from jaxcal.diagnosis.residuals.noise import by_unit
from jaxcal.model import Model

ONSET_GRID = 128  # onsets scanned per unit (every row of a shorter unit)
# a step through a model's states costs one simulation per onset: a coarser grid
ONSET_GRID_DYNAMIC = 48
_RIDGE = 1e-9
# a static model's candidate columns kept once made: a pair's, and the candidate an
# overlap test compares with the rest (each a fleet's rows times its columns)
COLUMNS_KEPT = 4


class UnitScores(NamedTuple):
    """Per-unit screening statistics of one candidate (``U`` units)."""

    lr: np.ndarray  # [U] LR_u (a step: at its best onset)
    estimate: np.ndarray  # [U] coefficient (natural steps) of a one-column effect
    variance: np.ndarray  # [U] its variance
    onset: np.ndarray  # [U] best onset row (steps), -1 otherwise
    onset_ci: np.ndarray  # [U, 2] rows of the onset's 95 % interval (steps)


def choose_carriers(lr: np.ndarray, per_carrier: float) -> tuple[np.ndarray, float]:
    """``(carriers, criterion)``: the units with the largest ``lr``, as many as
    maximise ``sum lr - |C| per_carrier - 2 ln C(U, |C|)``; empty when no subset
    has a positive criterion."""
    u = lr.size
    order = np.argsort(-lr, kind="stable")
    m = np.arange(1, u + 1)
    log_binom = gammaln(u + 1) - gammaln(m + 1) - gammaln(u - m + 1)
    crit = np.cumsum(lr[order]) - m * per_carrier - 2.0 * log_binom
    best = int(np.argmax(crit))
    if crit[best] <= 0:
        return np.zeros(0, int), 0.0
    return np.sort(order[: best + 1]), float(crit[best])


def spec_for(declared, members: Sequence[Candidate], initial_state=False) -> ModelSpec:
    """The model: declared + the members in their forms."""
    return ModelSpec(tuple(declared), tuple(members), initial_state)


def init_from(null: FitResult, model: Model, data: LoopData, spec: ModelSpec):
    """Start a candidate fit at the declared-only solution, the effects at zero."""
    lay = layout(model, data, spec)
    u, q0 = null.params.unit_coef.shape
    unit_coef = np.zeros((u, lay.num_local))
    unit_coef[:, :q0] = null.params.unit_coef
    return ModelParams(unit_coef, np.zeros(lay.num_global))


def warm_from(prev: FitResult, model: Model, data: LoopData, spec: ModelSpec):
    """Start a candidate fit where ``prev`` (an earlier fit of the same entry, e.g.
    the last noise pass's) ended: its coefficients of every block ``spec`` shares
    with it (a term in the same form, carriers and onsets, its coefficients rescaled
    to the same physical size when the natural step moved with the noise), zeros
    elsewhere; ``None`` when it shares no term or its units differ."""
    lay, old = layout(model, data, spec), prev.layout
    if prev.params.unit_coef.shape[0] != data.num_units:
        return None
    old_terms = {c.key: c for c in prev.spec.terms}
    new_terms = {c.key: c for c in spec.terms}
    old_blocks = {(b.role, b.name): b for b in old.blocks}
    unit_coef = np.zeros((data.num_units, lay.num_local))
    global_coef = np.zeros(lay.num_global)
    shared = 0
    for b in lay.blocks:
        ob = old_blocks.get((b.role, b.name))
        if ob is None or ob.local != b.local:
            continue
        ratio = 1.0
        if b.role == "term":
            new_c, old_c = new_terms[b.name], old_terms[b.name]
            if dataclasses.replace(old_c, scale=new_c.scale) != new_c:
                continue
            ratio = old_c.scale / new_c.scale
            shared += 1
        if b.local:
            coef = prev.params.unit_coef[:, ob.columns]
            unit_coef[:, b.columns] = coef if ratio == 1.0 else coef * ratio
        else:
            coef = prev.params.global_coef[ob.columns]
            global_coef[b.columns] = coef if ratio == 1.0 else coef * ratio
    return ModelParams(unit_coef, global_coef) if shared == len(new_terms) else None


class Screen:
    """Linearised scores of candidate sets at the declared-only fit ``null``.

    The columns it scores (the declared ones, each candidate's, a step's at its best
    onsets) are a fleet's rows times their columns each. A static model's are made
    when read, from the linearisation at ``null`` that holds every candidate's
    derivatives, and only the last few are kept; :meth:`release` drops them before
    the refits (which need none) and a later read makes them again, the same bits.
    """

    def __init__(self, model: Model, data: LoopData, library, null: FitResult):
        self.model, self.data, self.null = model, data, null
        ev = null.evaluation
        self.r = ev.white
        self.used = ev.used
        self.log_n = float(np.log(max(null.num_resid, 2)))
        self.library = list(library)
        # each unit's rows (outputs flattened) on one [U, rows * S, ...] layout, zero
        # past its end: per-unit products are batched matrix products
        self._width = int(np.diff(data.starts).max())
        self._decl, self._decl_u_cols = None, None  # made when read (.decl, ._decl_u)
        self._r_u = self._by_unit(self.r)[..., 0]
        gram = self._decl_u.transpose(0, 2, 1) @ self._decl_u
        self._a_inv = np.linalg.inv(gram + 1e-6 * np.eye(gram.shape[1]))
        self._d = (self._decl_u.transpose(0, 2, 1) @ self._r_u[..., None])[..., 0]
        self._base = {}  # key -> whitened columns on every unit [N, S, k]
        self._every = {}  # key -> the smooth candidate on every unit
        self._like = None  # a static model's evaluation at null, every derivative
        # a static model's linearisation at null with every candidate's derivatives
        self.null_lin = None
        smooth = [c.with_form("units", range(data.num_units))
                  for c in self.library if c.kind.profile != "step"]  # fmt: skip
        if smooth:
            self._smooth_columns(smooth)
        self._steps = {}  # key -> (UnitScores, whitened column at the best onsets)

    @property
    def decl(self) -> np.ndarray:
        """The declared coefficients' prewhitened columns ``[N, S, q0]`` at null."""
        if self._decl is None:
            cols = columns_of(self.null.evaluation)
            self._decl = cols[:, :, : self.null.layout.num_local]
        return self._decl

    @property
    def _decl_u(self) -> np.ndarray:
        """:attr:`decl` on the per-unit layout ``[U, width * S, q0]``."""
        if self._decl_u_cols is None:
            self._decl_u_cols = self._by_unit(self.decl)
        return self._decl_u_cols

    def release(self) -> None:
        """Drop the columns a static model's screen can make again (the declared
        ones, the candidates', the steps' at their onsets); the scores stay."""
        if self.model.is_stateful:
            return  # made by simulations: kept
        self._decl, self._decl_u_cols, self._base = None, None, {}
        self._steps = {k: (scores, None) for k, (scores, _) in self._steps.items()}

    def _rows(self, u: int) -> slice:
        return slice(self.data.starts[u], self.data.starts[u + 1])

    def _smooth_columns(self, smooth: Sequence[Candidate]) -> None:
        """Prepare each smooth candidate's whitened columns ``[N, S, k]`` on every
        unit: a model with memory's all at once (one simulation along every tangent,
        kept), a static model's from one evaluation with every derivative, each
        candidate's formed when read (:meth:`_smooth`)."""
        self._every = {c.name: c for c in smooth}
        if self.model.is_stateful:
            widths = [term_profile(self.data, c).shape[1] for c in smooth]
            cols, ends = self._columns(smooth), np.cumsum(widths)
            for c, k, e in zip(smooth, widths, ends, strict=True):
                self._base[c.name] = cols[:, :, e - k : e]
            return
        every = layout(self.model, self.data, ModelSpec((), tuple(smooth)))
        ev = self.null.evaluation
        self._like = signatures(self.model, self.data, ev.inputs, (), like=ev.sig,
                                cover=every.tangents)  # fmt: skip
        self.null_lin = self._like.lin

    def _smooth(self, cand: Candidate) -> np.ndarray:
        """A smooth candidate's whitened columns on every unit; a static model keeps
        the :data:`COLUMNS_KEPT` read last (a model with memory: every one)."""
        cols = self._base.pop(cand.name, None)  # read: the newest again
        if cols is None:
            cols = self._columns([self._every[cand.name]], like=self._like)
            if len(self._base) >= COLUMNS_KEPT:
                self._base.pop(next(iter(self._base)))  # the least recently read
        self._base[cand.name] = cols
        return cols

    def _columns(self, members: Sequence[Candidate], *, like=None) -> np.ndarray:
        """Prewhitened signatures ``[N, S, q]`` of the members' coefficients at the
        null point (``like``: its evaluation with their derivatives)."""
        spec = ModelSpec((), tuple(members))
        tangents = layout(self.model, self.data, spec).tangents
        ev = self.null.evaluation
        like = ev.sig if like is None else like
        sig = signatures(self.model, self.data, ev.inputs, tangents, like=like)
        return self.data.whiten(np.where(self.used[:, :, None], sig.cols, 0.0))

    def _by_unit(self, arr: np.ndarray) -> np.ndarray:
        """``[N, S, ...]`` rows -> ``[U, width * S, k]``, zero past each unit's end."""
        out = by_unit(arr, self.data.starts, self._width)
        return out.reshape(self.data.num_units, self._width * arr.shape[1], -1)

    def project(self, cols: np.ndarray):
        """Per unit ``(M_u [U, q, q], s_u [U, q], raw_u [U, q, q])``: Gram and score
        of ``cols [N, S, q]`` after projecting out the declared columns, and the raw
        Gram."""
        z = self._by_unit(cols)
        zt = z.transpose(0, 2, 1)
        raw = zt @ z
        b = self._decl_u.transpose(0, 2, 1) @ z  # [U, q0, q]
        ab = self._a_inv @ b
        m = raw - b.transpose(0, 2, 1) @ ab
        s = zt @ self._r_u[..., None] - ab.transpose(0, 2, 1) @ self._d[..., None]
        return m, s[..., 0], raw

    # --------------------------------------------------------------- scores

    def unit_scores(self, cand: Candidate) -> UnitScores:
        """Per-unit statistics of ``cand`` (a step: scanned over onsets)."""
        if cand.kind.profile == "step":
            return self._step(cand)[0]
        m, s, _ = self.project(self._smooth(cand))
        u = self.data.num_units
        lr = np.einsum("ui,ui->u", (s[:, None, :] @ np.linalg.pinv(m))[:, 0], s)
        with np.errstate(all="ignore"):
            est = np.where(m[:, 0, 0] > 0, s[:, 0] / m[:, 0, 0], np.nan)
            var = np.where(m[:, 0, 0] > 0, 1.0 / m[:, 0, 0], np.nan)
        none = np.full(u, -1)
        return UnitScores(np.maximum(lr, 0.0), est, var, none, np.stack([none] * 2, 1))

    def fleet_score(self, cand: Candidate) -> tuple[float, float, float]:
        """``(LR, coefficient, variance)`` of ``cand`` in the fleet form."""
        m, s, _ = self.project(self._smooth(cand))
        mm, ss = float(m[:, 0, 0].sum()), float(s[:, 0].sum())
        if mm <= 0:
            return 0.0, np.nan, np.nan
        return ss**2 / mm, ss / mm, 1.0 / mm

    def per_carrier_penalty(self, cand: Candidate) -> float:
        """BIC price of one carrier of a units term: its coefficients (and onset)."""
        return cand.kind.num_free(self.data.num_candidate_knots) * self.log_n

    def units_form(self, cand: Candidate) -> tuple[Candidate | None, UnitScores]:
        """``cand`` in the units form on its chosen carriers (``None``: no unit)."""
        scores = self.unit_scores(cand)
        carriers, _ = choose_carriers(scores.lr, self.per_carrier_penalty(cand))
        if carriers.size == 0:
            return None, scores
        onsets = scores.onset[carriers] if cand.kind.profile == "step" else ()
        return cand.with_form("units", carriers, onsets), scores

    def form_columns(self, cand: Candidate) -> np.ndarray:
        """Prewhitened columns ``[N, S, k]`` of ``cand`` in its form."""
        if cand.kind.profile == "step":
            cols = self._step(cand)[1]
        else:
            cols = self._smooth(cand)
        if cand.per_unit:
            carries = np.zeros(self.data.num_units, bool)
            carries[list(cand.carriers)] = True
            cols = cols * carries[self.data.unit][:, None, None]
        return cols

    def joint(self, members: Sequence[Candidate]):
        """``(LR, local step [U, l], global step [g])`` of adding ``members`` (in their
        forms) jointly: units terms per unit, fleet terms shared."""
        local = [c for c in members if c.per_unit]
        glob = [c for c in members if not c.per_unit]
        cols = np.concatenate([self.form_columns(c) for c in local + glob], axis=2)
        m, s, _ = self.project(cols)
        nl = sum(self.form_columns(c).shape[2] for c in local)
        stats = GramStats(m, s, 0.0, nl)
        sol = schur_solve(stats, range(nl), range(cols.shape[2] - nl))
        return max(sol.reduction, 0.0), sol.local_step, sol.global_step

    def detectability(self, cand: Candidate) -> float:
        """Norm of the candidate's signature kept after projecting out the declared."""
        cols = self.form_columns(cand)
        m, _, raw = self.project(cols)
        tr = np.trace(raw.sum(0))
        return float(np.sqrt(max(np.trace(m.sum(0)), 0.0) / max(tr, 1e-300)))

    def overlap(self, cand_i: Candidate, cand_j: Candidate) -> float:
        """Share of i's fitted projected signal ``y_i`` that j's columns reproduce:
        ``R^2 = ||P_j y_i||^2 / ||y_i||^2`` (units terms project unit by unit)."""
        ci, cj = self.form_columns(cand_i), self.form_columns(cand_j)
        ki = ci.shape[2]
        m, s, _ = self.project(np.concatenate([ci, cj], axis=2))
        m_ii, m_ji, m_jj = m[:, :ki, :ki], m[:, ki:, :ki], m[:, ki:, ki:]
        if cand_i.per_unit:
            coef = (np.linalg.pinv(m_ii) @ s[:, :ki, None])[..., 0]
        else:
            coef = np.linalg.pinv(m_ii.sum(0)) @ s[:, :ki].sum(0)
            coef = np.broadcast_to(coef, (m.shape[0], ki))
        energy = np.einsum("ui,uij,uj->", coef, m_ii, coef)
        v = np.einsum("uji,ui->uj", m_ji, coef)
        if cand_j.per_unit:
            proj = float(
                np.einsum("ui,ui->", (v[:, None, :] @ np.linalg.pinv(m_jj))[:, 0], v)
            )
        else:
            vs = v.sum(0)
            proj = float(vs @ np.linalg.pinv(m_jj.sum(0)) @ vs)
        return float(proj / energy) if energy > 0 else 0.0

    # ---------------------------------------------------------------- steps

    def _grid(self, size: int = ONSET_GRID) -> np.ndarray:
        """``[U, size]`` onset positions (rows since the unit's first) scanned."""
        out = []
        for u in range(self.data.num_units):
            n = self.data.starts[u + 1] - self.data.starts[u]
            lo, hi = 1, max(n - 2, 1)
            g = np.unique(np.linspace(lo, hi, min(size, hi - lo + 1)).round())
            out.append(np.resize(g.astype(int), size))
        return np.stack(out)

    def _step(self, cand: Candidate):
        """Scan a step's onset in every unit (module docstring); cached."""
        if self._steps.get(cand.name, (None, None))[1] is not None:
            return self._steps[cand.name]
        channel, idx = cand.kind.channel, channel_index(self.model, cand)
        if self.model.is_stateful and not cand.kind.is_sensor:
            out = self._dynamic_step(cand, channel, idx)
        else:
            raw = self._raw(
                [Tangent(channel, idx, np.full(self.data.num_rows, cand.scale))]
            )
            out = self._static_step(raw[:, :, 0])
        self._steps[cand.name] = out
        return out

    def _best(self, stat, grid, ss, mm):
        """Per unit: the onset maximising ``stat [U, G]``, its estimate and interval."""
        first = self.data.starts[:-1]
        k = np.argmax(stat, axis=1)
        at = np.arange(stat.shape[0])
        lr = stat[at, k]
        near = stat >= (lr - ONSET_CI)[:, None]
        ci = np.stack([np.where(near, grid, np.iinfo(int).max).min(1),
                       np.where(near, grid, -1).max(1)], 1)  # fmt: skip
        with np.errstate(all="ignore"):
            est, var = ss[at, k] / mm[at, k], 1.0 / mm[at, k]
        return UnitScores(lr, est, var, first + grid[at, k], first[:, None] + ci), k

    def _static_step(self, raw: np.ndarray):
        """A step in a static model's input or an output, every unit and onset at
        once. The step from ``t0`` of the raw column ``a`` is ``a 1[t >= t0]``; its
        prewhitened rows are the whole column's ``W`` from ``t0 + p`` on (``p`` the
        AR order), zero before ``t0``, and ``p`` transient rows between that see the
        step's first rows alone. So each onset's products with the declared columns
        and the residual are suffix sums of the rows' products plus ``p`` rows:
        O(N) for all onsets, not O(N G). Every whitened entry has the bits of the
        step whitened alone; only the sums' order differs."""
        data, noise = self.data, self.data.noise
        pos, first = data.position, data.starts[:-1]
        grid = self._grid(ONSET_GRID)
        lags = int(noise.order.max())
        scale = noise.sigma * np.sqrt(noise.inflation)
        white = noise.whiten(raw, pos)  # [N, S]
        decl = self.decl  # [N, S, q]
        # per row: sum over outputs of W^2, D^T W, r W; suffix sums within units
        # on a [U, width] layout (zero past each unit's end)
        width = int(np.diff(data.starts).max()) + lags + 2
        per_row = np.concatenate([np.einsum("ts,ts->t", white, white)[:, None],
                                  np.einsum("ts,ts->t", self.r, white)[:, None],
                                  np.einsum("tsq,ts->tq", decl, white)], 1)  # fmt: skip
        suffix = np.cumsum(by_unit(per_row, data.starts, width)[:, ::-1], 1)[:, ::-1]
        at = np.arange(data.num_units)[:, None]
        sums = suffix[at, grid + lags]  # [U, G, 2 + q]
        # the transient rows t0 + j, j < p: the filter over the step's rows alone
        table = noise.filter_table(np.arange(width))  # [width, S, MAX_ORDER + 1]
        length = np.diff(data.starts)

        def transient(j, t, row):
            """Row ``t0 + j`` (position ``t``, row ``row``) of the step from ``t0``
            whitened: the filter over the step's rows alone."""
            z = table[t, :, 0] * raw[row]
            for k in range(1, j + 1):
                z = z + table[t, :, k] * raw[row - k]
            return z / scale

        for j in range(lags):
            t = grid + j  # [U, G] positions
            inside = t < length[:, None]
            row = np.where(inside, first[:, None] + t, 0)
            z = np.where(inside[:, :, None], transient(j, t, row), 0.0)  # [U, G, S]
            sums[:, :, 0] += np.einsum("ugs,ugs->ug", z, z)
            sums[:, :, 1] += np.einsum("ugs,ugs->ug", self.r[row], z)
            sums[:, :, 2:] += np.einsum("ugsq,ugs->ugq", decl[row], z)
        a_inv = self._a_inv
        b = sums[:, :, 2:]
        mm = sums[:, :, 0] - np.einsum("ugi,uij,ugj->ug", b, a_inv, b)
        ss = sums[:, :, 1] - np.einsum("ugi,uij,uj->ug", b, a_inv, self._d)
        with np.errstate(all="ignore"):
            stat = np.where(mm > _RIDGE, ss**2 / mm, 0.0)
        scores, k = self._best(stat, grid, ss, mm)
        onset = grid[np.arange(data.num_units), k][data.unit]  # per row
        best = np.where((pos >= onset + lags)[:, None], white, 0.0)
        for j in range(lags):  # the transient rows of the best onset
            rows = np.flatnonzero(pos == onset + j)
            best[rows] = transient(j, pos[rows], rows)
        return scores, best[:, :, None]

    def _dynamic_step(self, cand: Candidate, channel, idx):
        """A parameter step through a model's states: one tangent per onset, each
        unit's onsets whitened and projected together."""
        data = self.data
        pos = data.position
        grid = self._grid(ONSET_GRID_DYNAMIC)
        tangents = [
            Tangent(channel, idx, cand.scale * (pos >= grid[data.unit, g]))
            for g in range(grid.shape[1])
        ]
        raw = self._raw(tangents)
        num_u = data.num_units
        mm, ss = np.zeros((num_u, grid.shape[1])), np.zeros((num_u, grid.shape[1]))
        best_cols = np.zeros(data.x.shape + (1,))
        for u in range(num_u):
            sl = self._rows(u)
            p = pos[sl]
            white = data.noise.whiten(raw[sl], p - p[0])
            n, s_dim, g = white.shape
            z = white.reshape(n * s_dim, g)
            dm = self.decl[sl].reshape(-1, self.decl.shape[2])
            b = dm.T @ z
            mm[u] = np.sum(z * z, 0) - np.einsum("ig,ij,jg->g", b, self._a_inv[u], b)
            ss[u] = z.T @ self.r[sl].reshape(-1) - b.T @ self._a_inv[u] @ self._d[u]
            with np.errstate(all="ignore"):
                stat = np.where(mm[u] > _RIDGE, ss[u] ** 2 / mm[u], 0.0)
            best_cols[sl, :, 0] = white[:, :, int(np.argmax(stat))]
        with np.errstate(all="ignore"):
            stat = np.where(mm > _RIDGE, ss**2 / mm, 0.0)
        scores, _ = self._best(stat, grid, ss, mm)
        return scores, best_cols

    def _raw(self, tangents) -> np.ndarray:
        """Signatures ``[N, S, q]`` (not whitened) along ``tangents`` at the null."""
        ev = self.null.evaluation
        sig = signatures(self.model, self.data, ev.inputs, tangents, like=ev.sig)
        return np.where(self.used[:, :, None], sig.cols, 0.0)
