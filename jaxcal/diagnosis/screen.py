"""Linearised screening of candidate effects at the declared-only solution.

At the declared-only fit, the normalised Jacobian columns of the declared spline
coefficients and of every candidate are accumulated per unit as Gram blocks
(:func:`.fitting.gram_stats`). The Gauss–Newton step of *any* subset of columns is then
a Schur-complement solve on those blocks, and its SSR reduction is the linearised
likelihood-ratio statistic of that subset (the score test of Rao 1948 in Gauss–Newton
form), so every single candidate and every pair is scored without another model
evaluation. The same blocks give each candidate's *detectability* (the share of its
signature's norm left after projecting out the declared parameters' signatures) and
the *overlap* of two candidates (the share of one's fitted signal that the other's
projected signature reproduces), used to flag confounding.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from jaxcal.diagnosis.effects import Candidate
from jaxcal.diagnosis.fitting import (
    FitResult,
    GramStats,
    ModelParams,
    ModelSpec,
    gram_stats,
    schur_solve,
    signature_columns,
)
from jaxcal.diagnosis.prepare import LoopData


def _split(members: Sequence[Candidate]):
    return [c for c in members if c.per_unit], [c for c in members if not c.per_unit]


def spec_for(declared: Sequence[str], members: Sequence[Candidate]) -> ModelSpec:
    """The model: declared + per-unit parameter members, global members as effects."""
    local, glob = _split(members)
    return ModelSpec(
        tuple(declared) + tuple(c.target for c in local), tuple(glob), len(declared)
    )


def init_from(null: FitResult, spec: ModelSpec, data: LoopData) -> ModelParams:
    """Start a candidate fit at the declared-only solution, the effects at zero."""
    u, q0 = null.params.unit_coef.shape
    extra = spec.local_size(data) - q0
    unit_coef = np.concatenate([null.params.unit_coef, np.zeros((u, extra))], axis=1)
    return ModelParams(unit_coef, np.zeros(len(spec.global_effects)))


class Screen:
    """Linearised scores of candidate sets at the declared-only solution ``null``.

    Column layout of the Gram blocks: the declared spline coefficients, then ``Kc``
    per parameter candidate (per unit), then one column per constant candidate.
    """

    def __init__(self, model, data: LoopData, declared, library, null: FitResult):
        self.data, self.library = data, list(library)
        per_unit = [c for c in library if c.per_unit]
        self.glob = [c for c in library if not c.per_unit]
        spec = spec_for(declared, per_unit + self.glob)
        local, glob = signature_columns(data, null.evaluation.lin, spec, model)
        self.stats: GramStats = gram_stats(
            data, null.evaluation.resid, null.evaluation.valid, local, glob
        )
        k, kc = data.num_knots, data.num_candidate_knots
        d0 = len(declared) * k
        self.decl = list(range(d0))
        self.local_pos = {
            c.name: list(range(d0 + i * kc, d0 + (i + 1) * kc))
            for i, c in enumerate(per_unit)
        }
        self.global_pos = {c.name: i for i, c in enumerate(self.glob)}
        self.base = schur_solve(self.stats, self.decl, []).reduction

    def cols(self, members) -> tuple[list[int], list[int]]:
        """(local, global) column indices of the declared columns plus ``members``."""
        local = self.decl + [
            j for c in members if c.per_unit for j in self.local_pos[c.name]
        ]
        glob = [self.global_pos[c.name] for c in members if not c.per_unit]
        return local, glob

    def score(self, members):
        """``(LR, SchurSolution)``: linearised SSR reduction of adding ``members``."""
        local, glob = self.cols(members)
        sol = schur_solve(self.stats, local, glob)
        return max(sol.reduction - self.base, 0.0), sol

    def detectability(self, cand: Candidate) -> float:
        """Norm of the candidate's signature kept after projecting out the declared."""
        local, glob = self.cols([cand])
        new = local[len(self.decl) :] if cand.per_unit else []
        raw_cols = new if cand.per_unit else [self.stats.num_local + glob[0]]
        raw = sum(
            np.trace(self.stats.gram[:, raw_cols][:, :, raw_cols], axis1=1, axis2=2)
        )
        proj = self.projected(local=new, glob=[] if cand.per_unit else glob)
        return float(np.sqrt(max(np.trace(proj.sum(0)), 0.0) / max(raw, 1e-300)))

    def projected(self, local, glob):
        """Per-unit Gram ``[U, q, q]`` of columns after projecting out the declared."""
        cols = np.asarray(list(local) + [self.stats.num_local + g for g in glob], int)
        d = np.asarray(self.decl, int)
        g = self.stats.gram
        a = g[:, d[:, None], d[None, :]] + 1e-6 * np.eye(d.size)
        b = g[:, d[:, None], cols[None, :]]
        return g[:, cols[:, None], cols[None, :]] - np.einsum(
            "uij,uik->ujk", b, np.linalg.solve(a, b)
        )

    def overlap(self, cand_i: Candidate, cand_j: Candidate) -> float:
        """Share of i's fitted projected signal ``y_i`` that j's columns reproduce.

        ``R^2 = ||P_j y_i||^2 / ||y_i||^2`` with ``y_i = P_D Z_i c_i`` (``P_D``
        projects out the declared columns, ``c_i`` is i's linearised fit) and ``P_j``
        the projection onto ``P_D Z_j``; per-unit columns project unit by unit.
        """
        _, sol = self.score([cand_i])
        nd = len(self.decl)
        coef_i = sol.local_step[:, nd:] if cand_i.per_unit else sol.global_step
        li, gi = self.cols([cand_i])
        lj, gj = self.cols([cand_j])
        m = self.projected(local=li[nd:] + lj[nd:], glob=gi + gj)
        ni = len(li) - nd + len(gi)
        m_ii, m_ji, m_jj = m[:, :ni, :ni], m[:, ni:, :ni], m[:, ni:, ni:]
        c_u = coef_i if cand_i.per_unit else np.broadcast_to(coef_i, (m.shape[0], ni))
        energy = np.einsum("ui,uij,uj->", c_u, m_ii, c_u)
        v = np.einsum("uji,ui->uj", m_ji, c_u)  # <P_D Z_j, y_i> per unit
        if cand_j.per_unit:
            ridge = 1e-9 * np.eye(m_jj.shape[1])
            proj = np.sum(v * np.linalg.solve(m_jj + ridge, v[:, :, None])[:, :, 0])
        else:
            vs = v.sum(0)
            proj = float(vs @ np.linalg.pinv(m_jj.sum(0)) @ vs)
        return float(proj / energy) if energy > 0 else 0.0
