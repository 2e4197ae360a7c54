"""The engine's F along one stream, warm-started from the previous sample.

A deployed calibrator evaluates F once per sample along a flight; the cold solve
(:func:`jaxcal.models.turbofan.physics.evaluation.evaluate_design`: Newton from the
guess table, each iteration a forward-mode Jacobian) is then its whole cost. Consecutive
samples are nearby problems, so the previous sample's solution, inverse Jacobian and
sensitivity to (w, theta) start Broyden's method
(:func:`jaxcal.models.turbofan.physics.solver.quasi_newton`), which closes the balance
with a few residuals and no Jacobian; the cold solve remains the fall-back, which a
fleet (under ``vmap``) runs only at the rows where some unit needs it (a batching rule
of its own, :func:`_hinted_solve`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcal.models.turbofan.physics import cycle, solver
from jaxcal.models.turbofan.physics.constants import CONDITION_NAMES, HEALTH_NAMES
from jaxcal.models.turbofan.physics.design import (
    DesignPoint,
    EngineDesign,
    design_point,
)
from jaxcal.models.turbofan.physics.evaluation import (
    EngineInfo,
    Envelope,
    default_solver_config,
    evaluate_design,
    in_envelope,
    physical,
    residual_fn,
    sensor_vector,
)
from jaxcal.models.turbofan.physics.guess import GuessTable
from jaxcal.precision import float_dtype

# Broyden updates per warm-started sample before falling back to the full solve: a
# flight's next sample closes in ~4-6 (experiments/cpubench/engine_latency.py).
HINT_MAX_ITER = 10


def evaluate_hinted(
    d: EngineDesign,
    w,
    theta,
    hint: solver.Hint,
    *,
    guess: GuessTable | None = None,
    envelope: Envelope = Envelope(),
    solver_cfg: solver.SolverConfig | None = None,
    dp: DesignPoint | None = None,
    max_iter: int = HINT_MAX_ITER,
):
    """One sample of :func:`evaluate_design`, warm-started along a stream.

    Why: a deployed calibrator calls F once per sample along a flight, and the cold
    solve (4 Newton iterations, each a forward-mode Jacobian) is its whole cost. From
    ``hint`` (the previous sample's solution, inverse Jacobian and sensitivity to
    (w, theta)) the start is the first-order prediction and Broyden's method
    (:func:`jaxcal.models.turbofan.physics.solver.quasi_newton`) closes the balance to
    the solver's ``tol`` with ~6 residual evaluations and no Jacobian (the residual with
    unrolled thermo loops, cheap when not differentiated). When it does not (no hint
    yet, a jump in the conditions, a NaN hint) the sample is solved as
    :func:`evaluate_design` does from the guess table (``lax.cond``: the cold path
    runs only then; under ``vmap``, for the whole batch, at the rows where some lane
    needs it),
    and the next hint carries the exact inverse Jacobian and sensitivity there. The
    outputs agree with the cold path's to the solve's tolerance (~3e-10 relative on
    Dataset #1), not bit for bit; ``info.converged`` is checked the same way (closed,
    finite, physical, inside the envelope). Not differentiable.

    Args:
        d, guess, envelope, solver_cfg, dp: as :func:`evaluate_design`.
        w: [4] one operating point; theta: [10].
        hint: :class:`jaxcal.models.turbofan.physics.solver.Hint`
            (``Engine.initial_hint()`` first).
        max_iter: Broyden updates before the fallback.

    Returns:
        (x [S], EngineInfo, next hint).
    """
    dtype = float_dtype()
    cfg = default_solver_config(dtype) if solver_cfg is None else solver_cfg
    w, theta = jnp.asarray(w, dtype), jnp.asarray(theta, dtype)
    if w.shape != (len(CONDITION_NAMES),) or theta.shape != (len(HEALTH_NAMES),):
        raise ValueError(
            f"evaluate_hinted takes one sample: w [4], theta [10], got "
            f"{tuple(w.shape)}, {tuple(theta.shape)} (vmap it for a batch)"
        )
    dp = design_point(d) if dp is None else dp
    hint = solver.Hint(
        *(jnp.asarray(a, bool if i == 2 else dtype) for i, a in enumerate(hint))
    )
    solve = _hinted_solve(envelope, cfg, max_iter)
    x, info, jinv, dz_dp = solve(w, theta, hint, (d, dp, guess))
    p = jnp.concatenate([w, theta])
    return x, info, solver.Hint(info.z, jinv, info.converged, p, dz_dp)


def _hinted_solve(envelope, cfg, max_iter):
    """``solve(w, theta, hint, (d, dp, guess)) -> (x, EngineInfo, jinv, dz_dp)``:
    Broyden from the hint, the cold solve where it does not close (``lax.cond``).

    Under ``vmap`` a ``cond`` on a batched predicate runs both branches for every
    lane, so a fleet would pay the cold solve (4 Newton iterations, each a
    forward-mode Jacobian) at every row on top of Broyden's. The batching rule
    (``jax.custom_batching.custom_vmap``) runs Broyden on the whole batch and the
    cold solve, on the whole batch, only when some lane needs it (its first row, a
    jump, a NaN hint): each lane gets what the ``cond`` gives it, and a fleet's
    row costs about a stream's. ``results/bench/stream_profile.md``, round 4. The
    engine's arrays are arguments, not closures: a rule's function may not close
    over a traced value.
    """

    def fast(w, theta, hint, consts):
        d, dp, _ = consts
        effects = jnp.zeros((cycle.NUM_EFFECTS,), w.dtype)
        p = jnp.concatenate([w, theta])
        usable = _is_usable(hint)
        residual = _residual_with_outputs(d, dp, w, theta, effects)
        z0 = jnp.where(usable, solver.predicted_start(hint, p), 0.0)
        start = hint._replace(z=z0, jinv=jnp.where(usable, hint.jinv, 0.0))
        z, rmax, iters, jinv, (x, is_physical) = solver.quasi_newton(
            residual, start, None, cfg.tol, max_iter
        )
        inside = in_envelope(envelope, w, theta)
        ok = usable & (rmax <= cfg.tol) & jnp.all(jnp.isfinite(x)) & is_physical
        info = EngineInfo(inside, rmax, iters, inside, z)
        return (x, info, jinv, solver.secant_sensitivity(hint, p, z)), ok

    def cold(w, theta, consts):
        d, dp, guess = consts
        effects = jnp.zeros((cycle.NUM_EFFECTS,), w.dtype)
        p = jnp.concatenate([w, theta])
        return _cold_solve(d, dp, w, theta, effects, p, guess, envelope, cfg)

    @jax.custom_batching.custom_vmap
    def solve(w, theta, hint, consts):
        out, ok = fast(w, theta, hint, consts)
        return jax.lax.cond(ok, lambda _: out, lambda _: cold(w, theta, consts), None)

    @solve.def_vmap
    def _batched(size, batched, w, theta, hint, consts):
        def spread(a, is_batched):
            return a if is_batched else jnp.broadcast_to(a, (size, *jnp.shape(a)))

        w, theta = spread(w, batched[0]), spread(theta, batched[1])
        hint = jax.tree.map(spread, hint, batched[2])
        axes = jax.tree.map(lambda b: 0 if b else None, batched[3])
        out, ok = jax.vmap(fast, in_axes=(0, 0, 0, axes))(w, theta, hint, consts)

        def with_cold(_):
            def pick(a, b):
                return jnp.where(ok.reshape(ok.shape + (1,) * (a.ndim - 1)), a, b)

            cold_out = jax.vmap(cold, in_axes=(0, 0, axes))(w, theta, consts)
            return jax.tree.map(pick, out, cold_out)

        out = jax.lax.cond(jnp.all(ok), lambda _: out, with_cold, None)
        return out, jax.tree.map(lambda _: True, out)

    return solve


def _is_usable(hint: solver.Hint):
    """``[]`` bool: the hint closed its sample and every array of it is finite."""
    usable = hint.ok
    for a in (hint.z, hint.jinv, hint.p, hint.dz_dp):
        usable = usable & jnp.all(jnp.isfinite(a))
    return usable


def _residual_with_outputs(d: EngineDesign, dp: DesignPoint, w, theta, effects):
    """``residual(z, _) -> (r, (x [S], physical))``, the balance with unrolled
    thermo loops and the sample's outputs, for Broyden's method."""

    def balance(z):
        return cycle.balance(d, dp, w, theta, effects, z, unroll=True)

    def one(z):
        r, st = balance(z)
        return r, (sensor_vector(d, st, w), physical(st))

    def residual(z, _):
        # as a batch of one: XLA:CPU fuses [1]-shaped chains into fewer kernels than
        # 0-d scalars; the outputs come with every residual, so the last iterate's
        # are returned without one more balance
        return jax.tree.map(lambda a: a[0], jax.vmap(one)(z[None]))

    return residual


def _cold_solve(d, dp, w, theta, effects, p, guess, envelope, cfg):
    """``(x, EngineInfo, jinv, dz_dp)`` of the cold solve from the guess table
    (:func:`evaluate_design`), with the exact inverse Jacobian and the sensitivity
    to ``p = [w, theta]`` at its solution for the next hint."""
    xc, info = evaluate_design(
        d, w, theta, guess=guess, envelope=envelope, solver_cfg=cfg, dp=dp
    )
    jac = jax.jacfwd(residual_fn)(info.z, (d, dp, w, theta, effects))
    dr_dp = jax.jacfwd(lambda q: residual_fn(info.z, (d, dp, q[:4], q[4:], effects)))(p)
    jinv = jnp.linalg.inv(jac)
    return xc, info, jinv, -jinv @ dr_dp
