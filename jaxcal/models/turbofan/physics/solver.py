"""Damped Newton solve of the off-design balance with implicit-function gradients.

The balance r(z; p) = 0 (9 unknowns) is solved by Newton's method with a dense
forward-mode Jacobian, LU solve, a step clipped to ||dz||_inf <= ``max_step`` and a
best-of-three backtracking line search (alpha in {1, 1/2, 1/4}), inside a
``lax.while_loop`` that stops at ``tol`` or ``max_iter`` (physics_facts.md 3.3, "Newton
tips for JAX"). Under ``vmap`` the loop runs until every sample has stopped; finished
samples are frozen by the batching rule of ``while_loop``.

Derivatives never go through the iterations: :func:`solve` is a ``jax.custom_jvp`` whose
tangent is the implicit-function theorem, dz = -J_z^{-1} (dr/dp) dp at the solution, so
``jacfwd`` and ``grad`` (by transposition of the linear tangent) both work and cost one
extra linear solve. J_z is the one the loop formed at the accepted iterate (the same
function at the same point), and :func:`solve_closed` carries the outputs' dy/dz beside
it, so that a differentiated program holds the balance's forward-mode program twice (in
the loop, and for the parameters at the solution) rather than four times (J_z again, the
parameters', the outputs' at the solution): the turbofan's linearisation program of the
diagnosis fell from 143 k to 93 k optimised HLO lines and its loaded executable from 490
to 317 MB (``results/loop/profile.md``, round 14).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """Static Newton settings."""

    max_iter: int = 40  # hard cap on Newton iterations
    tol: float = 1e-11  # stop when max |r| (normalised residuals) is below this
    max_step: float = 0.5  # clip ||dz||_inf per iteration (unbounded coordinates)


class SolveInfo(NamedTuple):
    residual_norm: jnp.ndarray  # max |r| at the returned z
    iterations: jnp.ndarray  # Newton iterations used


def _newton(fn, z0, params, cfg: SolverConfig):
    """Newton with step clipping and accept/reject backtracking on ||r||_2, for
    ``fn(z, params) -> (r [n], y [m])``: the residual ``r`` and outputs ``y`` whose
    derivative ``dy/dz`` is carried beside ``dr/dz`` (``m = 0``: none).

    One residual + Jacobian evaluation per iteration: a trial point that does not
    lower ||r||_2 is rejected and the step from the last accepted point is halved (down
    to 1/16, then accepted anyway so that the iteration cannot stall). Returns ``z``,
    :class:`SolveInfo` and ``(dr/dz, dy/dz)`` at the accepted iterate (NaN until one is
    accepted: ``z0`` has none).
    """

    def cond(carry):
        it, rmax = carry[0], carry[3]
        return (it < cfg.max_iter) & (rmax > cfg.tol)

    def body(carry):
        it, z_acc, merit_acc, _, dz, alpha, z_try, jac_acc = carry
        jac, (r, _) = jax.jacfwd(lambda zz: (fn(zz, params),) * 2, has_aux=True)(z_try)
        merit = jnp.sum(r**2)
        merit = jnp.where(jnp.isfinite(merit), merit, jnp.inf)
        accept = (merit < merit_acc) | (alpha < 0.07)
        step = -jnp.linalg.solve(jac[0], r)
        step = jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
        step = step * jnp.minimum(1.0, cfg.max_step / (jnp.max(jnp.abs(step)) + 1e-300))
        z_acc = jnp.where(accept, z_try, z_acc)
        rmax = jnp.where(accept, jnp.max(jnp.abs(r)), carry[3])
        merit_acc = jnp.where(accept, merit, merit_acc)
        dz = jnp.where(accept, step, dz)
        alpha = jnp.where(accept, 1.0, 0.5 * alpha)
        jac_acc = jax.tree.map(lambda a, b: jnp.where(accept, a, b), jac, jac_acc)
        return it + 1, z_acc, merit_acc, rmax, dz, alpha, z_acc + alpha * dz, jac_acc

    inf = jnp.array(jnp.inf, z0.dtype)
    r0, y0 = jax.eval_shape(fn, z0, params)
    jac0 = tuple(jnp.full(a.shape + z0.shape, jnp.nan, z0.dtype) for a in (r0, y0))
    init = (jnp.int32(0), z0, inf, inf, jnp.zeros_like(z0), jnp.ones((), z0.dtype), z0,
            jac0)  # fmt: skip
    it, z, _, rmax, *_, jac = jax.lax.while_loop(cond, body, init)
    return z, SolveInfo(residual_norm=rmax, iterations=it), jac


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 3))
def _solved(fn, z0, params, cfg):
    """:func:`_newton`'s ``z``, Jacobians, iterations and residual norm (floats), with
    their own implicit tangents: the Jacobians' is traced only when a derivative is
    differentiated again (reverse over forward, as a Hessian is)."""
    z, info, jac = _newton(fn, z0, params, cfg)
    return z, jac, info.iterations.astype(z.dtype), info.residual_norm


@_solved.defjvp
def _solved_jvp(fn, cfg, primals, tangents):
    z0, params = primals
    _, dparams = tangents
    z, jac, iters, rmax = _solved(fn, z0, params, cfg)
    _, (dr, _) = jax.jvp(lambda p: fn(z, p), (params,), (dparams,))
    dz = -jnp.linalg.solve(jac[0], dr)

    def jacobians(zz, p):
        return jax.jacfwd(lambda q: fn(q, p))(zz)

    _, djac = jax.jvp(jacobians, (z, params), (dz, dparams))
    zero = jnp.zeros_like
    return (z, jac, iters, rmax), (dz, djac, zero(iters), zero(rmax))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 3))
def _closed(balance_fn, z0, params, cfg):
    # not differentiated: the loop forms no output derivative (an empty y)
    def residual(z, p):
        return balance_fn(z, p)[0], jnp.zeros((0,), z.dtype)

    z, info, _ = _newton(residual, z0, params, cfg)
    _, y, aux = balance_fn(z, params)
    # iteration count and residual norm travel as floats so that they can carry a
    # (zero) tangent; the norm is the one of the accepted iterate, computed in the loop
    return z, y, aux, info.iterations.astype(z.dtype), info.residual_norm


@_closed.defjvp
def _closed_jvp(balance_fn, cfg, primals, tangents):
    z0, params = primals
    _, dparams = tangents

    def outputs(z, p):
        return balance_fn(z, p)[:2]

    z, (jac_r, jac_y), iters, rmax = _solved(
        outputs, jax.lax.stop_gradient(z0), params, cfg
    )

    def at_solution(p):
        r, y, aux = balance_fn(z, p)
        return (r, y), aux

    (_, y), (dr, dy), aux = jax.jvp(at_solution, (params,), (dparams,), has_aux=True)
    dz = -jnp.linalg.solve(jac_r, dr)
    no_tangent = jax.tree.map(lambda a: np.zeros(np.shape(a), jax.dtypes.float0), aux)
    zero = jnp.zeros_like
    return (z, y, aux, iters, rmax), (dz, dy + jac_y @ dz, no_tangent, zero(iters),
                                      zero(rmax))  # fmt: skip


def solve_closed(
    balance_fn: Callable, z0, params, cfg: SolverConfig = SolverConfig()
) -> tuple:
    """Solve ``r(z, params) = 0`` from ``z0`` and return the outputs there;
    differentiable w.r.t. ``params``, outputs included.

    Args:
        balance_fn: pure function ``(z [n], params pytree) -> (r [n], y [m], aux)``:
            the residuals, the outputs ``y`` (differentiable) and ``aux`` (a pytree
            of booleans, not differentiable) at ``z``.
        z0: [n] initial guess (no gradient flows through it).
        params: pytree of arrays the solution depends on (differentiable).
        cfg: static solver settings.

    Returns:
        ``(z [n], y [m], aux, SolveInfo)`` at the returned (last accepted) iterate;
        the tangent of ``y`` is ``dy/dp dp + dy/dz dz`` (module docstring).
    """
    z, y, aux, iters, rmax = _closed(balance_fn, z0, params, cfg)
    info = SolveInfo(
        residual_norm=jax.lax.stop_gradient(rmax),
        iterations=jax.lax.stop_gradient(iters).astype(jnp.int32),
    )
    return z, y, aux, info


def solve(
    residual_fn: Callable, z0, params, cfg: SolverConfig = SolverConfig()
) -> tuple[jnp.ndarray, SolveInfo]:
    """``(z [n], SolveInfo)``: :func:`solve_closed` of ``residual_fn(z, params) ->
    residuals [n]`` with no outputs (differentiable w.r.t. ``params``)."""

    def balance_fn(z, p):
        return residual_fn(z, p), jnp.zeros((0,), z.dtype), ()

    z, _, _, info = solve_closed(balance_fn, z0, params, cfg)
    return z, info


# ------------------------------------------------------------------ warm starts


class Hint(NamedTuple):
    """A warm start for :func:`quasi_newton`: a nearby solution and its derivatives.

    Attributes:
        z: ``[n]`` the solution of a nearby problem (e.g. the previous sample's).
        jinv: ``[n, n]`` an approximate inverse Jacobian dr/dz at ``z``.
        ok: ``[]`` bool, False when the hint carries nothing (use the cold solve).
        p: ``[m]`` the problem's inputs ``z`` solves (e.g. conditions and theta).
        dz_dp: ``[n, m]`` approximate sensitivity of the solution to ``p``: the
            next start is the first-order prediction ``z + dz_dp (p_next - p)``.
    """

    z: jnp.ndarray
    jinv: jnp.ndarray
    ok: jnp.ndarray
    p: jnp.ndarray
    dz_dp: jnp.ndarray


def empty_hint(n: int, m: int, dtype=jnp.float64) -> Hint:
    """A hint that says "no warm start" (``ok`` False) for n unknowns, m inputs."""
    zeros = functools.partial(jnp.zeros, dtype=dtype)
    return Hint(
        zeros((n,)), zeros((n, n)), jnp.zeros((), bool), zeros((m,)), zeros((n, m))
    )


def predicted_start(hint: Hint, p) -> jnp.ndarray:
    """``z + dz_dp (p - hint.p)``: the hint's first-order start for inputs ``p``."""
    return hint.z + hint.dz_dp @ (p - hint.p)


def secant_sensitivity(hint: Hint, p, z) -> jnp.ndarray:
    """dz_dp updated so that it maps ``p - hint.p`` onto ``z - hint.z`` (Broyden's
    rank-one update, unchanged when p did not move)."""
    dp = p - hint.p
    miss = (z - hint.z) - hint.dz_dp @ dp
    den = dp @ dp
    update = jnp.outer(miss, dp) / jnp.where(den > 0.0, den, 1.0)
    return hint.dz_dp + jnp.where(den > 0.0, update, 0.0)


def quasi_newton(residual_fn: Callable, hint: Hint, params, tol: float, max_iter: int):
    """Broyden's ("good") method from a warm start, no Jacobian evaluation at all.

    Along a stream of nearby problems (a flight's consecutive samples) the previous
    solution and inverse Jacobian are a start from which a few residual evaluations
    close the balance: each iteration costs one residual (no forward-mode sweep),
    and the rank-one update of the inverse keeps it tracking the drifting Jacobian
    (a chord iteration with the stale Jacobian needed ~7 evaluations per sample,
    experiments/cpubench/engine_latency.py). It does not clip or backtrack: a start
    it cannot handle simply does not reach ``tol`` in ``max_iter`` and the caller
    falls back to :func:`solve`. Not differentiable (deployment only).

    Args:
        residual_fn: ``(z [n], params) -> (r [n], aux)``; ``aux`` (any pytree, e.g.
            the outputs computed on the way) is returned for the last iterate, so
            the caller need not evaluate the problem once more there.
        hint: :class:`Hint` (``ok`` is not read here).
        params: pytree passed to ``residual_fn``.
        tol: stop when max |r| <= tol.
        max_iter: cap on the updates (residual evaluations = iterations + 1).

    Returns:
        ``(z [n], rmax [], iterations [] int32, jinv [n, n], aux)`` at the last
        iterate; ``rmax`` is its max |r| (a non-finite r gives inf).
    """
    hint = jax.tree.map(jax.lax.stop_gradient, hint)

    def rmax_of(r):
        m = jnp.max(jnp.abs(r))
        return jnp.where(jnp.isfinite(m), m, jnp.inf)

    def cond(carry):
        it, _, r, _, _ = carry
        rm = rmax_of(r)
        return (it < max_iter) & (rm > tol) & jnp.isfinite(rm)

    def body(carry):
        it, z, r, jinv, _ = carry
        s = -jinv @ r
        z_new = z + s
        r_new, aux = residual_fn(z_new, params)
        hy = jinv @ (r_new - r)
        den = s @ hy
        update = jnp.outer(s - hy, s @ jinv) / den
        keep = (jnp.abs(den) > 1e-300) & jnp.all(jnp.isfinite(update))
        jinv = jnp.where(keep, jinv + update, jinv)
        return it + 1, z_new, r_new, jinv, aux

    r0, aux0 = residual_fn(hint.z, params)
    it, z, r, jinv, aux = jax.lax.while_loop(
        cond, body, (jnp.int32(0), hint.z, r0, hint.jinv, aux0)
    )
    return z, rmax_of(r), it, jinv, aux
