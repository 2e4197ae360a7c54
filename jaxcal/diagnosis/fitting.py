"""Joint Gauss–Newton fit of per-unit declared parameters and constant effects.

The model of a data set is ``y_t = G(w_t, theta_u(c_t), phi) (+ offset_t)``: the
extended model of :mod:`jaxcal.diagnosis.effects` with, per unit ``u``, the fitted
parameters ``theta_u(c) = nominal + scale sum_k B_k(c) a_uk`` (B-splines in time,
:mod:`.problem`; ``scale`` the parameter's natural step, :func:`.effects.natural_scale`)
and a few constant effects ``phi = scale * b`` shared by all units. The normalised
residual
``r = (x - y) / sigma`` is minimised by Levenberg–Marquardt (Nocedal & Wright 2006, sec.
10.3) with Marquardt damping ``lambda diag(J^T J)``.

The normal equations have arrow structure: each unit's coefficients couple only to its
own rows and to the shared ``b``. :func:`schur_solve` eliminates the unit blocks
(Schur complement; Triggs et al. 2000, bundle adjustment, sec. 6.1), so a fit of 260
units costs 260 small solves plus one of the size of ``b``. The Jacobian blocks are
stored per unit as Gram matrices (:class:`GramStats`), which also gives the linearised
likelihood-ratio of *any* subset of candidate columns at once (used by
:mod:`.identify`). Model evaluations are jitted (:func:`.effects.linearize`); the
block algebra runs in numpy on the host because the number of units and rows varies
from data set to data set.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from jaxcal.diagnosis.effects import (
    LAYER_NAMES,
    Candidate,
    Linearization,
    linearize,
    natural_scale,
    offset_conditions,
)
from jaxcal.diagnosis.prepare import LoopData
from jaxcal.model import Model

_RIDGE = 1e-6  # on unit coefficients (1 = one natural step): keeps empty knots finite


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """Which parameters a fit moves.

    Attributes:
        unit_params: model parameters fitted per unit as splines (declared first).
        global_effects: constant effects shared by all units.
        num_declared: the first ``num_declared`` unit parameters use the declared
            basis ``data.basis``, the others ``data.basis_candidate`` (``None``: all
            use the declared basis).
    """

    unit_params: tuple[str, ...]
    global_effects: tuple[Candidate, ...] = ()
    num_declared: int | None = None

    def unit_blocks(self, data: LoopData) -> list[tuple[str, np.ndarray]]:
        """``(modifier, basis [N, K_j])`` per unit parameter, in coefficient order."""
        n = len(self.unit_params) if self.num_declared is None else self.num_declared
        return [
            (name, data.basis if j < n else data.basis_candidate)
            for j, name in enumerate(self.unit_params)
        ]

    def local_size(self, data: LoopData) -> int:
        """Coefficients per unit ``sum_j K_j``."""
        return sum(b.shape[1] for _, b in self.unit_blocks(data))

    def num_params(self, data: LoopData) -> int:
        """Number of fitted coefficients ``U sum_j K_j + m``."""
        return data.num_units * self.local_size(data) + len(self.global_effects)


class ModelParams(NamedTuple):
    """Fitted coefficients in natural steps (``theta = nominal + scale a``,
    ``phi = scale b``)."""

    unit_coef: np.ndarray  # [U, sum_j K_j], parameter-major
    global_coef: np.ndarray  # [m]


class Evaluation(NamedTuple):
    """The model at one parameter point."""

    yhat: np.ndarray  # [N, S] model output (sensor units, offset included)
    resid: np.ndarray  # [N, S] normalised residual, 0 on invalid rows
    valid: np.ndarray  # [N] bool
    ssr: float  # sum of squared normalised residuals over valid rows
    theta: np.ndarray  # [N, P_all] model parameters used
    lin: Linearization


class FitResult(NamedTuple):
    """Outcome of :func:`fit_model`."""

    spec: ModelSpec
    params: ModelParams
    evaluation: Evaluation
    ssr: float
    num_params: int
    num_resid: int  # valid rows x sensors
    global_cov: np.ndarray  # [m, m] covariance of phi (physical units, sigma known)
    iterations: int
    converged: bool

    @property
    def bic(self) -> float:
        """Schwarz criterion ``-2 log L + k ln n`` (known sigma, constants dropped)."""
        return self.ssr + self.num_params * np.log(max(self.num_resid, 2))

    def global_values(self) -> np.ndarray:
        """``[m]`` fitted effect sizes in physical units."""
        scale = np.array([c.scale for c in self.spec.global_effects])
        return scale * self.params.global_coef


def zero_params(data: LoopData, spec: ModelSpec) -> ModelParams:
    """All coefficients zero (nominal parameters, no effect)."""
    return ModelParams(
        np.zeros((data.num_units, spec.local_size(data))),
        np.zeros(len(spec.global_effects)),
    )


def model_inputs(model: Model, data: LoopData, spec: ModelSpec, params: ModelParams):
    """``(theta [N, P_all], effects [n_eff], layer [3, E], w_offset [W])`` of the
    extended model."""
    names = model.parameter_names
    theta = np.tile(model.nominal, (data.num_rows, 1))
    start = 0
    for name, basis in spec.unit_blocks(data):
        coef = params.unit_coef[data.unit, start : start + basis.shape[1]]  # [N, K_j]
        step = natural_scale(model, name)
        theta[:, names.index(name)] += step * np.sum(coef * basis, axis=1)
        start += basis.shape[1]
    effects = np.zeros(len(model.effects))
    effect_names = [e.name for e in model.effects]
    layer = np.zeros((len(LAYER_NAMES), len(model.outputs)))
    w_offset = np.zeros(len(model.conditions))
    for cand, b in zip(spec.global_effects, params.global_coef, strict=True):
        value = cand.scale * b
        if cand.family == "effect":
            effects[effect_names.index(cand.target)] += value
        elif cand.family == "condition_offset":
            w_offset[model.condition_names.index(cand.target)] += value
        elif cand.family in LAYER_NAMES:
            s = model.output_names.index(cand.target)
            layer[LAYER_NAMES.index(cand.family), s] += value
        else:
            raise ValueError(f"{cand.name}: a per-unit candidate cannot be global")
    return theta, effects, layer, w_offset


def evaluate_model(
    model: Model,
    data: LoopData,
    spec: ModelSpec,
    params: ModelParams,
    *,
    offset: np.ndarray | None = None,
    valid: np.ndarray | None = None,
) -> Evaluation:
    """Run the extended model at ``params`` (rows outside ``valid`` get r = 0)."""
    theta, effects, layer, w_offset = model_inputs(model, data, spec, params)
    lin = linearize(model, data.w, theta, effects, layer, data.tau, w_offset)
    yhat = lin.y[:, data.sensor_idx]
    if offset is not None:
        yhat = yhat + offset
    ok = lin.ok if valid is None else valid & lin.ok
    resid = np.where(ok[:, None], (data.x - yhat) / data.noise_std, 0.0)
    ssr = float(np.sum(resid**2))
    if valid is not None and np.any(valid & ~lin.ok):
        ssr = np.inf  # a row that was fine before failed: reject this point
    return Evaluation(yhat, resid, ok, ssr, theta, lin)


def signature_columns(
    data: LoopData,
    lin: Linearization,
    spec: ModelSpec,
    model: Model,
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised Jacobian columns ``dr/dcoef`` (with a minus sign dropped).

    Returns:
        ``(local [N, S, sum_j K_j], glob [N, S, m])``: per-unit spline columns
        (parameter major, knot minor) and the columns of the constant effects.
    """
    sig = data.noise_std
    global_effects = spec.global_effects
    local = []
    for name, basis in spec.unit_blocks(data):
        jac = lin.jac_theta[:, data.sensor_idx, model.parameter_names.index(name)]
        step = natural_scale(model, name)
        local.append((step * jac / sig)[:, :, None] * basis[:, None, :])
    local = np.concatenate(local, axis=2) if local else np.zeros(data.x.shape + (0,))
    glob = np.zeros(data.x.shape + (len(global_effects),))
    names = list(data.sensor_names)
    effect_names = [e.name for e in model.effects]
    for c, cand in enumerate(global_effects):
        if cand.family == "effect":
            e = effect_names.index(cand.target)
            glob[:, :, c] = cand.scale * lin.jac_effects[:, data.sensor_idx, e] / sig
        elif cand.family == "condition_offset":
            j = offset_conditions(model).index(cand.target)
            glob[:, :, c] = cand.scale * lin.jac_w[:, data.sensor_idx, j] / sig
        else:
            s = names.index(cand.target)
            f = LAYER_NAMES.index(cand.family)
            col = lin.jac_layer[:, f, data.sensor_idx[s]]
            glob[:, s, c] = cand.scale * col / sig[s]
    return local, glob


class GramStats(NamedTuple):
    """Per-unit normal-equation blocks of the columns ``Z = [local | glob]``."""

    gram: np.ndarray  # [U, Q, Q] Z_u^T Z_u
    score: np.ndarray  # [U, Q] Z_u^T r_u
    ssr: float
    num_local: int  # the first columns are per-unit


def gram_stats(
    data: LoopData, resid: np.ndarray, valid: np.ndarray, local, glob
) -> GramStats:
    """Accumulate :class:`GramStats` unit by unit (bounded memory)."""
    z = np.concatenate([local, glob], axis=2) * valid[:, None, None]
    q = z.shape[2]
    gram = np.zeros((data.num_units, q, q))
    score = np.zeros((data.num_units, q))
    for u in range(data.num_units):
        sl = slice(data.starts[u], data.starts[u + 1])
        zu = z[sl].reshape(-1, q)
        gram[u] = zu.T @ zu
        score[u] = zu.T @ resid[sl].reshape(-1)
    return GramStats(gram, score, float(np.sum(resid**2)), local.shape[2])


class SchurSolution(NamedTuple):
    """A Gauss–Newton step of :func:`schur_solve`."""

    local_step: np.ndarray  # [U, l]
    global_step: np.ndarray  # [g]
    schur: np.ndarray  # [g, g] reduced normal matrix of the global columns
    reduction: float  # predicted SSR reduction of the (damped) linear step


def schur_solve(
    stats: GramStats,
    local_idx: Sequence[int],
    global_idx: Sequence[int],
    *,
    damping: float = 0.0,
) -> SchurSolution:
    """Solve the (damped) normal equations for a subset of columns by Schur complement.

    Args:
        stats: per-unit Gram blocks.
        local_idx: per-unit columns used (indices into the local part).
        global_idx: shared columns used (indices into the global part).
        damping: Marquardt lambda.

    Returns:
        :class:`SchurSolution`. Undamped, ``reduction`` is the exact SSR reduction of
        the linearised least-squares problem: the likelihood-ratio statistic.
    """
    li = np.asarray(local_idx, int)
    gi = stats.num_local + np.asarray(global_idx, int)
    units = stats.gram.shape[0]
    a_mat = stats.gram[:, li[:, None], li[None, :]]
    a_mat = a_mat + (damping * np.einsum("uii->ui", a_mat) + _RIDGE)[
        :, :, None
    ] * np.eye(li.size)
    b_mat = stats.gram[:, li[:, None], gi[None, :]]
    c_mat = stats.gram[:, gi[:, None], gi[None, :]].sum(0)
    c_mat = c_mat + damping * np.diag(np.diag(c_mat))
    a_vec, b_vec = stats.score[:, li], stats.score[:, gi].sum(0)
    if li.size:
        sol = np.linalg.solve(a_mat, np.concatenate([b_mat, a_vec[:, :, None]], axis=2))
        ainv_b, ainv_a = sol[:, :, : gi.size], sol[:, :, gi.size]
        schur = c_mat - np.einsum("uij,uik->jk", b_mat, ainv_b)
        rhs = b_vec - np.einsum("uij,ui->j", b_mat, ainv_a)
    else:
        ainv_b, ainv_a = np.zeros((units, 0, gi.size)), np.zeros((units, 0))
        schur, rhs = c_mat, b_vec
    dg = np.linalg.lstsq(schur, rhs, rcond=1e-12)[0] if gi.size else np.zeros(0)
    du = ainv_a - np.einsum("uij,j->ui", ainv_b, dg)
    reduction = float(np.sum(du * a_vec) + dg @ b_vec)
    return SchurSolution(du, dg, schur, reduction)


def _columns(data, model, spec, lin):
    return signature_columns(data, lin, spec, model)


def fit_model(
    model: Model,
    data: LoopData,
    spec: ModelSpec,
    init: ModelParams | None = None,
    *,
    offset: np.ndarray | None = None,
    max_iters: int = 20,
    rtol: float = 1e-7,
) -> FitResult:
    """Levenberg–Marquardt fit of ``spec`` to the data.

    Rows on which the model fails at the start point are left out for the whole fit;
    a trial point that makes another row fail is rejected like one that raises the cost.

    Args:
        model: the model.
        data: the rows.
        spec: parameters to fit.
        init: start point (default zeros).
        offset: ``[N, S]`` fixed additive term (a discrepancy, sensor units).
        max_iters: upper bound on accepted + rejected steps.
        rtol: stop when an accepted step lowers the SSR by less than ``rtol * SSR``.

    Returns:
        :class:`FitResult`; ``global_cov`` is ``(J^T J)^-1`` of the shared effects in
        physical units (sigma known), from the Schur complement at the solution.
    """
    params = zero_params(data, spec) if init is None else init
    ev = evaluate_model(model, data, spec, params, offset=offset)
    valid = ev.valid
    if not valid.any():
        raise ValueError(
            f"model {model.name!r} is invalid (non-finite or outside its valid "
            "input range) on every row of the data"
        )
    local_idx = np.arange(spec.local_size(data))
    global_idx = np.arange(len(spec.global_effects))
    damping, converged, it = 1e-3, False, 0
    stats = gram_stats(data, ev.resid, valid, *_columns(data, model, spec, ev.lin))
    while it < max_iters:
        it += 1
        step = schur_solve(stats, local_idx, global_idx, damping=damping)
        trial = ModelParams(
            params.unit_coef + step.local_step, params.global_coef + step.global_step
        )
        ev_t = evaluate_model(model, data, spec, trial, offset=offset, valid=valid)
        if np.isfinite(ev_t.ssr) and ev_t.ssr <= ev.ssr:
            gain = ev.ssr - ev_t.ssr
            params, ev = trial, ev_t
            stats = gram_stats(
                data, ev.resid, valid, *_columns(data, model, spec, ev.lin)
            )
            damping = max(damping / 10.0, 1e-9)
            if gain <= rtol * max(ev.ssr, 1.0):
                converged = True
                break
        else:
            damping *= 10.0
            if damping > 1e8:
                break
    final = schur_solve(stats, local_idx, global_idx)
    scale = np.array([c.scale for c in spec.global_effects])
    cov = (
        np.linalg.pinv(final.schur, rcond=1e-12) * np.outer(scale, scale)
        if global_idx.size
        else np.zeros((0, 0))
    )
    return FitResult(
        spec,
        params,
        ev,
        ev.ssr,
        spec.num_params(data),
        int(valid.sum()) * data.num_sensors,
        cov,
        it,
        converged,
    )
