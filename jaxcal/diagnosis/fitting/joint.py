"""Joint Gauss–Newton fit of per-unit declared parameters and candidate effects.

The model of a data set is the extended model of
:mod:`jaxcal.diagnosis.kinds.signatures` with the terms of a
:class:`~jaxcal.diagnosis.kinds.terms.ModelSpec`: per unit ``u`` the declared
parameters ``theta_u(c) = nominal + scale sum_k B_k(c) a_uk`` (B-splines in time,
:mod:`jaxcal.diagnosis.data.prepare`; ``scale`` the natural step), for a model with
memory an offset of each unit's initial state, and the candidate effects
(:mod:`jaxcal.diagnosis.kinds.table`), each coefficient a column
(:mod:`jaxcal.diagnosis.kinds.terms`).

The fit minimises the sum of squares of the **prewhitened** residual (the noise model's
AR filter per output, :mod:`jaxcal.diagnosis.residuals.noise`: generalised least
squares), so its SSR is ``-2 log L`` up to a constant and every likelihood-ratio
statistic and standard error below accounts for the serial correlation of the noise.
Levenberg–Marquardt (Nocedal & Wright 2006, sec. 10.3) with Marquardt damping ``lambda
diag(J^T J)``: the damping's moves, the acceptance rule and the covariance are the one
solver core's (:mod:`jaxcal.numerics.levenberg_marquardt`); the loop runs on the host
and solves its own normal equations, because their structure is what makes the fit
affordable.

The normal equations have arrow structure: each unit's coefficients couple only to its
own rows and to the shared ones. :func:`schur_solve` eliminates the unit blocks
(Schur complement; Triggs et al. 2000, sec. 6.1), so a fit of 260 units costs 260 small
solves plus one of the size of the shared part. The Jacobian blocks are stored per unit
as Gram matrices (:class:`GramStats`), which also give the linearised likelihood ratio
of any subset of columns at once (:mod:`jaxcal.diagnosis.fitting.screen`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.kinds.linearization import Linearization, remember
from jaxcal.diagnosis.kinds.signatures import RowInputs, Signatures, signatures
from jaxcal.diagnosis.kinds.table import Candidate
from jaxcal.diagnosis.kinds.terms import (
    Layout,
    ModelParams,
    ModelSpec,
    layout,
    model_inputs,
    num_params,
    selection_penalty,
    zero_params,
)
from jaxcal.model import Model
from jaxcal.numerics.levenberg_marquardt import (
    Damping,
    inverse_psd,
    is_accepted,
    next_damping,
)

RIDGE = 1e-6  # on unit coefficients (1 = one natural step): keeps empty knots finite
# The fit's box: each parameter's bounds widened by this share of their range on each
# side; a positive quantity (a resistance, a capacity) keeps at least half its lower
# bound and a negative one at most half its upper bound. An effect the declared
# parameters cannot follow otherwise drives them to where the model has no meaning
# (a resistance at zero), while a departure beyond the stated range stays possible
# and is flagged.
FIT_BOX_MARGIN = 0.5
# a quantity of one sign: its log range times this, away from zero (fit_box)
FIT_BOX_AWAY = 1.0
_TO_BOUNDARY = 0.95  # a step that would leave the box goes this share of the way
_DAMPING = Damping(init=1e-3, shrink=10.0, grow=10.0, low=1e-9)
_GIVE_UP = 1e8  # the fit stops when a rejection takes the damping above this


class Evaluation(NamedTuple):
    """The model at one parameter point."""

    yhat: np.ndarray  # [N, S] model output (output units, offset included)
    resid: np.ndarray  # [N, S] residual / marginal noise std, 0 where not used
    white: np.ndarray  # [N, S] prewhitened, standardised residual
    used: np.ndarray  # [N, S] bool: observed and the model valid
    valid: np.ndarray  # [N] bool: the model valid
    ssr: float  # sum of squares of the prewhitened residual
    theta: np.ndarray  # [N, P_all] model parameters used
    inputs: RowInputs
    sig: Signatures
    # [N, S, L + G] prewhitened signatures, or None: not taken, or released once a
    # fit is done (:func:`columns_of` makes them again)
    cols: np.ndarray | None
    whiten: Callable | None = None  # the prewhitening ``cols`` were made with
    # a static model's raw signatures made again from its Jacobians (no model
    # evaluation): its ``sig.cols`` are released once whitened (:func:`raw_columns_of`)
    remake: Callable | None = None


class FitResult(NamedTuple):
    """Outcome of :func:`fit_model`."""

    spec: ModelSpec
    params: ModelParams
    evaluation: Evaluation
    layout: Layout
    ssr: float
    num_params: int
    num_resid: int  # used entries (rows x outputs)
    selection: float  # extended-BIC price of the units terms' carriers
    global_cov: np.ndarray  # [G, G] covariance of the shared terms, physical units
    iterations: int
    converged: bool

    @property
    def bic(self) -> float:
        """``-2 log L + k ln n`` (+ the carriers' price; sigma known)."""
        return (
            self.ssr + self.num_params * np.log(max(self.num_resid, 2)) + self.selection
        )

    def term_values(self, cand: Candidate) -> np.ndarray:
        """A term's fitted value(s) in physical units: ``[1]`` for a fleet term,
        ``[U, k]`` for a units term (zeros off its carriers)."""
        block = next(b for b in self.layout.blocks if b.name == cand.key)
        if block.local:
            return cand.scale * self.params.unit_coef[:, block.columns]
        return cand.scale * self.params.global_coef[block.columns]


def evaluate_model(
    model: Model,
    data: LoopData,
    lay: Layout,
    params: ModelParams,
    *,
    offset: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    columns: bool = True,
) -> Evaluation:
    """The extended model at ``params``: residuals, prewhitened residual and (with
    ``columns``) the prewhitened signatures. Rows outside ``valid`` get r = 0, and a
    row that was valid and fails makes the SSR infinite (the point is rejected)."""
    inputs = model_inputs(model, data, lay, params)
    # signatures cost a forward pass per tangent (a model with memory) or a
    # derivative per direction (a static one): taken only when asked for
    sig = signatures(model, data, inputs, lay.tangents if columns else ())
    yhat = sig.y if offset is None else sig.y + offset
    ok = sig.ok if valid is None else valid & sig.ok
    used = data.observed & ok[:, None]
    raw = np.where(used, data.x - yhat, 0.0)
    white = data.whiten(raw)
    ssr = float(np.sum(white**2))
    if valid is not None and np.any(valid & ~sig.ok):
        ssr = np.inf
    remake = None
    if columns and sig.lin is not None:  # the Jacobians alone: not these columns
        remake = functools.partial(_remake, model, data, inputs, lay.tangents, sig.lin)
    ev = Evaluation(
        yhat, raw / data.noise_std, white, used, ok, ssr, inputs.theta, inputs, sig,
        None, data.whiten if columns else None, remake,
    )  # fmt: skip
    if not columns:
        return ev
    ev = ev._replace(cols=columns_of(ev))  # always a new array (the whitening's)
    if remake is not None:  # the raw ones are made again when read: not held twice
        ev = ev._replace(sig=sig._replace(cols=None))
    return ev


def _remake(model, data, inputs, tangents, lin) -> np.ndarray:
    """A static model's raw signatures along ``tangents`` from its Jacobians ``lin``
    (the same operations as when they were first made: the same bits)."""
    return signatures(model, data, inputs, tangents, like=Signatures(None, None, None,
                      None, lin)).cols  # fmt: skip


def local_remake(model: Model, data: LoopData, fit: FitResult) -> Callable | None:
    """A static model's raw per-unit signatures ``[N, S, L]`` at ``fit``'s end point,
    made again from its Jacobians when called (``None``: a model with memory). It
    holds the coefficients, not the rows: a slimmed fit (:mod:`.identify`) is kept
    for a noise refit that may never read it."""
    lin = fit.evaluation.sig.lin
    if lin is None:
        return None
    return functools.partial(_remake_local, model, data, fit.layout, fit.params, lin)


def _remake_local(model, data, lay: Layout, params, lin) -> np.ndarray:
    inputs = model_inputs(model, data, lay, params)  # the fit's own: the same bits
    return _remake(model, data, inputs, lay.tangents[: lay.num_local], lin)


def raw_columns_of(ev: Evaluation) -> np.ndarray | None:
    """``ev``'s raw signatures ``sig.cols [N, S, L + G]``: kept, or made again from a
    static model's Jacobians once a finished fit released them (:func:`fit_model`)."""
    if ev.sig.cols is not None or ev.remake is None:
        return ev.sig.cols
    return ev.remake()


def columns_of(ev: Evaluation) -> np.ndarray | None:
    """``ev``'s prewhitened signatures ``[N, S, L + G]``: kept, or made from its raw
    ones with the prewhitening they were first made with (the same bits). A finished
    fit releases them (:func:`fit_model`): a fleet's rows times its columns each, read
    again by a few verdicts only."""
    if ev.cols is not None or ev.whiten is None:
        return ev.cols
    raw = raw_columns_of(ev)  # whitening writes a new array: no masked copy if all used
    return ev.whiten(raw if ev.used.all() else np.where(ev.used[..., None], raw, 0.0))


def resume_at(
    model: Model, data: LoopData, fit: FitResult, lin: Linearization | None = None
) -> None:
    """Keep the model's linearisation at ``fit``'s end point (or ``lin``, taken at
    the same point with more derivatives) as the latest evaluated point
    (:func:`~jaxcal.diagnosis.kinds.linearization.remember`): a fit that starts there
    (the same entry under another noise model or discrepancy offset, a candidate at
    the declared-only solution with its terms at zero) finds its first evaluation
    without evaluating the fleet. A model with memory keeps none."""
    lin = fit.evaluation.sig.lin if lin is None else lin
    if lin is not None and not model.is_stateful:
        remember(model, data, model_inputs(model, data, fit.layout, fit.params), lin)


def fit_box(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """``(low [P], high [P])``: the box the fit keeps every parameter in.

    The declared bounds widened by :data:`FIT_BOX_MARGIN` of their range on each
    side; a quantity of one sign (a resistance, a capacity) is also widened on the
    log scale and keeps its sign: toward zero by the same share of its log range,
    the nearer of the two bounds holding; away from zero by :data:`FIT_BOX_AWAY` of
    it, the farther holding (a bound ratio of 4: half the low bound, four times the
    high one): a parameter of one sign far beyond its high bound stays within reach
    rather than being read as another effect.
    """
    low = np.array([p.low for p in model.parameters], np.float64)
    high = np.array([p.high for p in model.parameters], np.float64)
    margin = FIT_BOX_MARGIN * (high - low)
    add_low, add_high = low - margin, high + margin
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(low > 0, high / low, np.where(high < 0, low / high, 1.0))
    ratio = np.where(np.isfinite(ratio) & (ratio > 1), ratio, 1.0)
    widen, away = ratio**FIT_BOX_MARGIN, ratio**FIT_BOX_AWAY
    pos, neg = low > 0, high < 0
    # toward zero the nearer of the two bounds, away from it the farther
    box_low = np.where(
        pos,
        np.maximum(add_low, low / widen),
        np.where(neg, np.minimum(add_low, low * away), add_low),
    )
    box_high = np.where(
        neg,
        np.minimum(add_high, high / widen),
        np.where(pos, np.maximum(add_high, high * away), add_high),
    )
    return box_low, box_high


def _into_box(model, data, lay, params, trial, box) -> ModelParams:
    """``trial`` moved back along the step so that no row's parameter leaves ``box``
    (fraction to the boundary; the parameters are linear in the coefficients)."""
    theta0 = model_inputs(model, data, lay, params).theta
    theta1 = model_inputs(model, data, lay, trial).theta
    delta = theta1 - theta0
    low, high = box
    with np.errstate(divide="ignore", invalid="ignore"):
        outward = np.where(delta > 0, high - theta0, low - theta0)
        room = np.where(delta != 0, outward / delta, np.inf)
    t = float(np.min(room, initial=np.inf))
    if t >= 1.0:
        return trial
    t = max(_TO_BOUNDARY * t, 0.0)
    return ModelParams(
        params.unit_coef + t * (trial.unit_coef - params.unit_coef),
        params.global_coef + t * (trial.global_coef - params.global_coef),
    )


class GramStats(NamedTuple):
    """Per-unit normal-equation blocks of the columns ``Z = [local | glob]``."""

    gram: np.ndarray  # [U, Q, Q] Z_u^T Z_u
    score: np.ndarray  # [U, Q] Z_u^T r_u
    ssr: float
    num_local: int  # the first columns are per-unit


def gram_stats(
    data: LoopData, white: np.ndarray, cols: np.ndarray, num_local: int
) -> GramStats:
    """Accumulate :class:`GramStats` of prewhitened ``cols [N, S, Q]`` and residual
    ``white [N, S]`` unit by unit (bounded memory)."""
    q = cols.shape[2]
    gram = np.zeros((data.num_units, q, q))
    score = np.zeros((data.num_units, q))
    for u in range(data.num_units):
        sl = slice(data.starts[u], data.starts[u + 1])
        zu = cols[sl].reshape(-1, q)
        gram[u] = zu.T @ zu
        score[u] = zu.T @ white[sl].reshape(-1)
    return GramStats(gram, score, float(np.sum(white**2)), num_local)


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
    a_mat = a_mat + (damping * np.einsum("uii->ui", a_mat) + RIDGE)[
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


def _evaluate_trial(model, data, lay, trial, offset, valid, ssr):
    """The trial point's evaluation: its SSR first, its signatures only when it
    lowers the SSR below ``ssr`` (those of a rejected point are never needed). A
    static model's derivatives come with its evaluation at a few percent each, and
    most trials are accepted: taken at once."""
    ev_t = evaluate_model(
        model, data, lay, trial, offset=offset, valid=valid,
        columns=not model.is_stateful,
    )  # fmt: skip
    if is_accepted(ev_t.ssr, ssr) and ev_t.cols is None:
        # the signatures too: a point where they overflow (a model with memory
        # driven unstable along a tangent) is rejected like a worse one
        ev_t = evaluate_model(model, data, lay, trial, offset=offset,
                              valid=valid)  # fmt: skip
    return ev_t


def _global_covariance(stats, spec: ModelSpec, local_idx, global_idx) -> np.ndarray:
    """``(J^T J)^-1`` of the shared terms in physical units, from the Schur
    complement of the undamped system at the solution."""
    final = schur_solve(stats, local_idx, global_idx)
    scale = np.array([c.scale for c in spec.global_terms])
    schur = 0.5 * (final.schur + final.schur.T)  # symmetric up to rounding
    return (
        np.asarray(inverse_psd(schur, rcond=1e-12)) * np.outer(scale, scale)
        if global_idx.size
        else np.zeros((0, 0))
    )


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
    """Levenberg–Marquardt fit of ``spec`` to the data (module docstring).

    Rows on which the model fails at the start point are left out for the whole fit;
    a trial point that makes another row fail is rejected like one that raises the cost.
    No step takes a parameter out of :func:`fit_box` (a step that would is shortened
    to the boundary).

    Args:
        model: the model.
        data: the rows (with their noise model).
        spec: what to fit.
        init: start point (default zeros).
        offset: ``[N, S]`` fixed additive term (a discrepancy, output units).
        max_iters: upper bound on accepted + rejected steps.
        rtol: stop when an accepted step lowers the SSR by less than ``rtol * SSR``.

    Returns:
        :class:`FitResult`; ``global_cov`` is ``(J^T J)^-1`` of the shared terms in
        physical units, from the Schur complement at the solution.
    """
    lay = layout(model, data, spec)
    params = zero_params(data, lay) if init is None else init
    ev = evaluate_model(model, data, lay, params, offset=offset)
    valid = ev.valid
    if not valid.any():
        raise ValueError(
            f"model {model.name!r} is invalid (non-finite or outside its valid "
            "input range) on every row of the data"
        )
    local_idx, global_idx = np.arange(lay.num_local), np.arange(lay.num_global)
    box = fit_box(model)
    damping, converged, it = _DAMPING.init, False, 0
    stats = gram_stats(data, ev.white, ev.cols, lay.num_local)
    while it < max_iters:
        step = schur_solve(stats, local_idx, global_idx, damping=damping)
        if damping <= _DAMPING.init and step.reduction <= rtol * max(ev.ssr, 1.0):
            # the linear model promises less than the stopping gain: converged
            # without evaluating the step (a fleet evaluation)
            converged = True
            break
        it += 1
        trial = ModelParams(
            params.unit_coef + step.local_step, params.global_coef + step.global_step
        )
        trial = _into_box(model, data, lay, params, trial, box)
        ev_t = _evaluate_trial(model, data, lay, trial, offset, valid, ev.ssr)
        accepted = bool(is_accepted(ev_t.ssr, ev.ssr))
        damping = float(next_damping(damping, accepted, _DAMPING))
        if accepted:
            gain = ev.ssr - ev_t.ssr
            params, ev = trial, ev_t
            stats = gram_stats(data, ev.white, ev.cols, lay.num_local)
            if gain <= rtol * max(ev.ssr, 1.0):
                converged = True
                break
        elif damping > _GIVE_UP:
            break
    cov = _global_covariance(stats, spec, local_idx, global_idx)
    if ev.whiten is not None:  # released: columns_of makes them again when read
        ev = ev._replace(cols=None)
    if ev.remake is not None:  # and raw_columns_of the raw ones
        ev = ev._replace(sig=ev.sig._replace(cols=None))
    return FitResult(
        spec, params, ev, lay, ev.ssr, num_params(data, spec, model),
        int(ev.used.sum()), selection_penalty(data, spec), cov, it, converged,
    )  # fmt: skip
