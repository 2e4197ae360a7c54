"""The one Levenberg–Marquardt core of jaxcal: damped Gauss–Newton and its covariance.

Every fit in jaxcal minimises ``0.5 ||r(y)||^2`` over ``y [P]`` (the fit's own, usually
scaled, coordinates) by Levenberg–Marquardt (Levenberg 1944, Marquardt 1963; Nocedal &
Wright 2006, sec. 10.3): a trial step solves ``(J^T J + lambda D) dy = -J^T r`` with
Marquardt's ``D = diag(J^T J)`` (floored); a trial with a finite cost no larger than
the current one is accepted and ``lambda`` shrinks, any other is rejected and
``lambda`` grows, so a failed model evaluation (a non-finite residual) never enters
``y``. The uncertainty of a solution is the Gauss–Newton (Laplace) covariance
``s^2 (J^T J)^-1``. This module owns all of it, once:

* :func:`linearize`: ``(r [M], J [M, P])`` from one ``jax.jacfwd`` pass;
* :func:`lm_iterate`: one trial step, optionally projected onto a box;
* :func:`lm_run`: a fixed number of steps (a streaming calibrator's fixed cost per
  sample: jittable, vmappable, fine inside ``lax.scan``); :func:`lm_solve`: to a
  tolerance in ``lax.while_loop``, with iteration count, status and cost history;
* :func:`marquardt_step`, :func:`is_accepted`, :func:`next_damping`: the rules, also
  driven from the host by a fit that solves its normal equations itself;
* :func:`inverse_psd`, :func:`gauss_newton_cov`: the covariance.

A residual may hand a *hint* from the last accepted point to the next evaluation
(``hinted=True`` in :func:`linearize`): the engine's Newton starts in the design fit,
a continuation in parameter space that keeps the balance on its physical branch.

Users: :mod:`jaxcal.calibrators.methods.ls.window` (sliding window and batch fit),
:mod:`jaxcal.calibrators.methods.ls.window_state` (moving horizon, box projection),
:mod:`jaxcal.models.turbofan.physics.design_fit` (hinted) and
:mod:`jaxcal.diagnosis.fitting.joint`, whose
normal equations have arrow structure and are solved by Schur complement on the host
with this module's damping, acceptance and covariance: a dense Jacobian there would
have one column block per unit (260 units in C-MAPSS FD002).

Why hand-written and not ``optimistix.LevenbergMarquardt`` (measured, optimistix
0.1.0 / lineax 0.1.1, jax 0.10.2, 2 CPU cores): on the streaming least squares of
``jaxcal.calibrate`` (heat exchanger, 4 units x 400 samples, window 32, 3 iterations
per sample) optimistix took 118 us per sample against 51 us here in float32 (91 vs
43 us in float64); 96 us with a normal-equations linear solver and 75 us driving
``solver.step`` in a fixed loop: 1.5-2.3x, over the 1.5x this core was allowed to
lose. Its step materialises the Jacobian from a linearisation for each linear solve
and again for the predicted reduction; here ``J`` is formed once per trial. Compile
times were alike (8.4 s vs 9.4 s) and so were the estimates where the parameters are
identified (the tank's theta RMSE to 1e-8). Where one is not, the damping differs:
optimistix damps with ``lambda I`` from ``lambda = 1``, this core with
``lambda diag(J^T J)`` from ``1e-3``; on the heat exchanger with the noise estimated
(``jaxcal.calibrate(..., method="ls")``, 4 units x 400 rows at the nominal theta,
float64) the fouling RMSE was 0.025 with optimistix and is 6.06 here, an unobserved
direction left almost undamped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from jaxcal.typedefs import Array

# ``resid_jac(y [P], hint) -> (r [M], J [M, P], hint')``: a linearised residual.
ResidJac = Callable[[Array, Any], tuple[Array, Array, Any]]
_DIAG_FLOOR = 1e-9  # Marquardt's D is floored at this share of its largest entry


@dataclasses.dataclass(frozen=True)
class Damping:
    """Marquardt's ``lambda``: where it starts and how it moves (static, hashable)."""

    init: float = 1e-3  # lambda at the first step
    shrink: float = 10.0  # lambda /= shrink after an accepted step
    grow: float = 10.0  # lambda *= grow after a rejected step
    low: float = 1e-12  # lambda stays in [low, high]
    high: float = 1e12

    def __post_init__(self):
        if not (self.init > 0 and self.shrink > 1 and self.grow > 1):
            raise ValueError(
                "Damping: need init > 0, shrink > 1 and grow > 1, got "
                f"{self.init}, {self.shrink}, {self.grow}"
            )
        if not 0 < self.low <= self.high:
            raise ValueError(
                f"Damping: need 0 < low <= high, got {self.low}, {self.high}"
            )


@dataclasses.dataclass(frozen=True)
class Tolerance:
    """When :func:`lm_solve` stops (scipy-like, in the fit's coordinates)."""

    max_iters: int = 100  # upper bound on trial steps
    gtol: float = 1e-10  # stop when ||J^T r||_inf <= gtol
    ftol: float = 1e-14  # stop when an accepted step lowers the cost by <= ftol * cost
    xtol: float = 1e-12  # stop when ||dy|| <= xtol * (xtol + ||y||)

    def __post_init__(self):
        name = type(self).__name__  # also a subclass's (FitConfig)
        if self.max_iters < 1:
            raise ValueError(f"{name}.max_iters must be >= 1, got {self.max_iters}")
        if min(self.gtol, self.ftol, self.xtol) < 0:
            raise ValueError(f"{name}: gtol, ftol and xtol must be >= 0")


class LMState(NamedTuple):
    """The iteration's state: the last accepted point and what was computed there."""

    y: Array  # [P] the point
    resid: Array  # [M] r(y)
    jac: Array  # [M, P] dr/dy at y
    cost: Array  # [] 0.5 ||r(y)||^2
    damping: Array  # [] Marquardt lambda for the next step
    hint: Any  # the residual's hint from y (None for a residual without one)


class LMStats(NamedTuple):
    """How :func:`lm_solve` went."""

    num_iters: Array  # [] int32, trial steps taken
    status: Array  # [] int32: 1 a tolerance met, 0 out of steps, -1 cost not finite
    costs: Array  # [max_iters + 1] the cost after each step (NaN after the last)


def linearize(residual: Callable, *, hinted: bool = False) -> ResidJac:
    """The residual and its Jacobian from one ``jax.jacfwd`` pass (the primal rides
    along as aux, so the model is evaluated once per point).

    Args:
        residual: ``r(y [P]) -> [M]``; with ``hinted``, ``r(y, hint) -> ([M], hint')``
            where ``hint'`` (not differentiated) is handed to the next evaluation
            if ``y`` is accepted.
        hinted: whether ``residual`` takes and returns a hint.

    Returns:
        ``resid_jac(y, hint) -> (r [M], J [M, P], hint')``.
    """

    def with_aux(y, hint):
        r, hint_out = residual(y, hint) if hinted else (residual(y), hint)
        return r, (r, hint_out)

    jac_fn = jax.jacfwd(with_aux, has_aux=True)

    def resid_jac(y, hint=None):
        jac, (r, hint_out) = jac_fn(y, hint)
        return r, jac, hint_out

    return resid_jac


def marquardt_step(jac: Array, resid: Array, damping: Array) -> Array:
    """The damped Gauss–Newton step ``dy [P]``: ``(J^T J + lambda D) dy = -J^T r``.

    ``D`` is the diagonal of ``J^T J`` floored at ``1e-9`` of its largest entry, so a
    parameter the residual ignores gets a finite (zero) step.

    Args:
        jac: ``[M, P]`` Jacobian at the current point.
        resid: ``[M]`` residual there.
        damping: ``[]`` Marquardt ``lambda``.
    """
    grad = jac.T @ resid
    hess = jac.T @ jac
    diag = jnp.diagonal(hess)
    diag = jnp.maximum(diag, _DIAG_FLOOR * jnp.max(diag) + jnp.finfo(diag.dtype).tiny)
    return jnp.linalg.solve(hess + damping * jnp.diag(diag), -grad)


def is_accepted(cost_try, cost):
    """A trial is accepted when its cost is finite and not larger than ``cost``."""
    return jnp.isfinite(cost_try) & (cost_try <= cost)


def next_damping(damping, accepted, schedule: Damping):
    """``lambda / shrink`` after an accepted step, ``lambda * grow`` after a rejected
    one, kept in ``[low, high]``."""
    new = jnp.where(accepted, damping / schedule.shrink, damping * schedule.grow)
    return jnp.clip(new, schedule.low, schedule.high)


def _cost(resid: Array) -> Array:
    return 0.5 * resid @ resid


def lm_init(resid_jac: ResidJac, y0: Array, schedule: Damping, hint=None) -> LMState:
    """The state at the start point ``y0 [P]`` (``hint``: the residual's first)."""
    resid, jac, hint = resid_jac(y0, hint)
    damping = jnp.asarray(schedule.init, y0.dtype)
    return LMState(y0, resid, jac, _cost(resid), damping, hint)


def lm_iterate(
    resid_jac: ResidJac,
    state: LMState,
    schedule: Damping,
    box: tuple[Array, Array] | None = None,
) -> tuple[LMState, Array, Array]:
    """One Levenberg–Marquardt trial step.

    Args:
        resid_jac: the linearised residual (:func:`linearize`).
        state: the current state.
        schedule: the damping's moves.
        box: ``(low [P], high [P])`` (``+-inf`` where free) or ``None``: the point
            after the step is projected onto it and the residual evaluated there.

    Returns:
        ``(state, accepted [] bool, step_norm [])``; ``step_norm`` is ``inf`` for a
        non-finite step.
    """
    dy = marquardt_step(state.jac, state.resid, state.damping)
    resid, jac, hint = resid_jac(state.y + dy, state.hint)
    cost = _cost(resid)
    finite_step = jnp.all(jnp.isfinite(dy))
    accepted = is_accepted(cost, state.cost) & finite_step

    def pick(new, old):
        return jnp.where(accepted, new, old)

    new = LMState(
        y=pick(state.y + dy, state.y),
        resid=pick(resid, state.resid),
        jac=pick(jac, state.jac),
        cost=pick(cost, state.cost),
        damping=next_damping(state.damping, accepted, schedule),
        hint=jax.tree.map(pick, hint, state.hint),
    )
    if box is not None:
        y = jnp.clip(new.y, *box)
        resid, jac, hint = resid_jac(y, new.hint)  # the projected point's own
        new = new._replace(y=y, resid=resid, jac=jac, cost=_cost(resid), hint=hint)
    step_norm = jnp.where(finite_step, jnp.linalg.norm(dy), jnp.inf)
    return new, accepted, step_norm


def lm_run(
    resid_jac: ResidJac,
    y0: Array,
    num_iters: int,
    schedule: Damping,
    *,
    hint=None,
    box: tuple[Array, Array] | None = None,
) -> LMState:
    """``num_iters`` steps from ``y0 [P]`` in ``lax.fori_loop``: a fixed cost of
    ``num_iters + 1`` linearisations (see :func:`lm_iterate` for ``box``)."""
    state = lm_init(resid_jac, y0, schedule, hint)
    return lax.fori_loop(
        0, num_iters, lambda _, s: lm_iterate(resid_jac, s, schedule, box)[0], state
    )


def lm_solve(
    resid_jac: ResidJac,
    y0: Array,
    tol: Tolerance,
    schedule: Damping,
    *,
    hint=None,
    box: tuple[Array, Array] | None = None,
    verbose: bool = False,
) -> tuple[LMState, LMStats]:
    """Steps from ``y0 [P]`` until a :class:`Tolerance` is met, in ``lax.while_loop``.

    Args:
        resid_jac: the linearised residual (:func:`linearize`).
        y0: ``[P]`` start point.
        tol: the stopping tests and ``max_iters``.
        schedule: the damping's start and moves.
        hint: the residual's first hint (a hinted residual).
        box: projection box (:func:`lm_iterate`).
        verbose: print each step's cost and damping (``jax.debug.print``).

    Returns:
        ``(state, LMStats)``; ``status`` is -1 when the cost is not finite (the start
        point already failed), 1 when ``gtol``, ``ftol`` or ``xtol`` was met.
    """

    def status_of(state, accepted, step_norm, cost_before):
        grad_norm = jnp.max(jnp.abs(state.jac.T @ state.resid))
        small_gain = accepted & (cost_before - state.cost <= tol.ftol * cost_before)
        small_step = step_norm <= tol.xtol * (tol.xtol + jnp.linalg.norm(state.y))
        done = (grad_norm <= tol.gtol) | small_gain | small_step
        return jnp.where(jnp.isfinite(state.cost), done.astype(jnp.int32), -1)

    def body(loop):
        state, it, _, costs = loop
        new, accepted, step_norm = lm_iterate(resid_jac, state, schedule, box)
        if verbose:
            jax.debug.print(
                "LM {it:3d} cost {c:.6g} lambda {d:.2g}", it=it, c=new.cost,
                d=new.damping,
            )  # fmt: skip
        status = status_of(new, accepted, step_norm, state.cost)
        return new, it + 1, status, costs.at[it + 1].set(new.cost)

    state0 = lm_init(resid_jac, y0, schedule, hint)
    status0 = status_of(state0, jnp.array(False), jnp.inf, state0.cost)
    costs0 = jnp.full((tol.max_iters + 1,), jnp.nan, state0.cost.dtype)
    loop0 = (state0, jnp.zeros((), jnp.int32), status0, costs0.at[0].set(state0.cost))
    state, num_iters, status, costs = lax.while_loop(
        lambda loop: (loop[2] == 0) & (loop[1] < tol.max_iters), body, loop0
    )
    return state, LMStats(num_iters, status, costs)


def inverse_psd(mat: Array, *, rcond: float | None = None) -> Array:
    """The inverse of a symmetric positive semi-definite matrix, from its eigenvalues.

    Args:
        mat: ``[P, P]``.
        rcond: ``None``: eigenvalues floored at ``eps * max(largest, 1)``, so an
            unidentified direction gets a huge, finite variance instead of NaN;
            a number: eigenvalues ``<= rcond * largest`` dropped (the Moore–Penrose
            pseudo-inverse, ``numpy.linalg.pinv``: zero variance there).

    Returns:
        ``[P, P]``.
    """
    eigval, eigvec = jnp.linalg.eigh(mat)
    if rcond is None:
        floor = jnp.finfo(mat.dtype).eps * jnp.maximum(jnp.max(eigval), 1.0)
        return (eigvec / jnp.maximum(eigval, floor)) @ eigvec.T
    kept = jnp.where(eigval > rcond * jnp.max(eigval), eigval, jnp.inf)
    return (eigvec / kept) @ eigvec.T


def gauss_newton_cov(jac: Array, *, s2=1.0, rcond: float | None = None) -> Array:
    """``s^2 (J^T J)^-1``: the Gauss–Newton (Laplace) covariance at a solution.

    Args:
        jac: ``[M, P]`` the residual's Jacobian at the solution.
        s2: the residual's variance: 1 for residuals in noise-std units, or the fit's
            own estimate ``2 cost / (M - P)``.
        rcond: as in :func:`inverse_psd`.

    Returns:
        ``[P, P]``.
    """
    return s2 * inverse_psd(jac.T @ jac, rcond=rcond)
