"""Fitting design constants to measured operating points (a calibration problem itself).

The unknowns are a chosen subset of :class:`EngineDesign` fields, written as
``value = nominal + scale * u`` with a standard-normal prior on ``u`` (the prior keeps
constants the data do not determine at their textbook values, physics_facts.md). The
data residuals are ``(x(w_k; design) - target)/sigma``. Levenberg-Marquardt on the
stacked residual vector is the one solver core's
(:mod:`jaxcal.numerics.levenberg_marquardt`, one jitted ``lax.while_loop``), with the
exact Jacobian ``jax.jacfwd`` through the implicit-function gradients of the Newton
solve (no finite differences). The engine's Newton starts ride along as the core's
hint: every evaluation starts from the solutions at the last accepted design
(continuation in design space, which keeps the balance on its physical branch while
the design moves), and a point where a solve does not converge is rejected.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.models.turbofan.physics.configs import design_from_flat, design_to_flat
from jaxcal.models.turbofan.physics.constants import SENSOR_NAMES
from jaxcal.models.turbofan.physics.design import (
    EngineDesign,
    corrected_fan_speed_demand,
    design_point,
)
from jaxcal.models.turbofan.physics.evaluation import evaluate_design
from jaxcal.models.turbofan.physics.guess import build_guess_table, initial_guess
from jaxcal.numerics.levenberg_marquardt import (
    Damping,
    Tolerance,
    gauss_newton_cov,
    linearize,
    lm_solve,
)


@dataclasses.dataclass(frozen=True)
class FitParam:
    """One fitted design constant with a standard-normal prior on ``u``.

    ``value = nominal + scale * u``, or ``nominal * exp(scale * u)`` when ``positive``
    (map slopes and curvatures whose sign is physics: a speed line must lose flow
    towards surge, an efficiency island must have a peak).
    """

    name: str  # flat name, e.g. "eta_fan_d" or "hpc.flow_speed_exp"
    scale: float
    positive: bool = False


@dataclasses.dataclass(frozen=True)
class Target:
    """One measured number: sensor ``sensor`` at condition ``k`` equals value +- sigma.

    With ``k_ref`` >= 0 the number is a *change*: x[k] - x[k_ref] (a degradation
    signature, for instance).
    """

    k: int
    sensor: str
    value: float
    sigma: float
    k_ref: int = -1


@dataclasses.dataclass(frozen=True)
class ThetaParam:
    """A health modifier fitted jointly with the design: theta[k, index] = scale * u."""

    k: int
    index: int
    scale: float


@dataclasses.dataclass(frozen=True)
class FitResult:
    design: EngineDesign
    u: np.ndarray
    cost_history: list[float]
    residuals: np.ndarray  # data residuals (normalised) at the optimum
    u_std: np.ndarray  # posterior std of u from (J^T J)^-1
    theta: np.ndarray  # fitted theta_params values


def make_residual_fn(
    base: EngineDesign,
    params: Sequence[FitParam],
    conditions: np.ndarray,
    thetas: np.ndarray,
    targets: Sequence[Target],
    prior_weight: float = 1.0,
    theta_params: Sequence[ThetaParam] = (),
):
    """Build r(u) = [data residuals; prior_weight * u] for LM.

    ``u`` holds the design parameters first, then the ``theta_params`` (whose prior is
    flat: they get no prior residual).
    """
    nominal = design_to_flat(base)
    centers = jnp.array([nominal[p.name] for p in params])
    scales = jnp.array([p.scale for p in params])
    positive = jnp.array([p.positive for p in params])
    idx_k = np.array([t.k for t in targets])
    idx_s = np.array([SENSOR_NAMES.index(t.sensor) for t in targets])
    values = jnp.array([t.value for t in targets])
    sigmas = jnp.array([t.sigma for t in targets])
    # Newton starts: the continuation table of the *nominal* design, interpolated once
    # (a start point needs no gradient, and the fitted design stays close to nominal)
    table = jax.jit(build_guess_table)(base, design_point(base))
    pcn, _ = corrected_fan_speed_demand(base, jnp.asarray(conditions)[:, 2])
    z0 = jax.vmap(initial_guess, (None, 0, 0))(
        table, pcn, jnp.asarray(conditions)[:, 1]
    )
    idx_ref = np.array([max(t.k_ref, 0) for t in targets])
    is_delta = jnp.array([t.k_ref >= 0 for t in targets])
    w = jnp.asarray(conditions)
    th0 = jnp.asarray(thetas)
    n_design = len(params)
    th_k = np.array([t.k for t in theta_params], dtype=int)
    th_i = np.array([t.index for t in theta_params], dtype=int)
    th_scale = jnp.array([t.scale for t in theta_params])

    def design_of(u):
        vals = jnp.where(positive, centers * jnp.exp(scales * u), centers + scales * u)
        return design_from_flat(base, {p.name: vals[i] for i, p in enumerate(params)})

    def residual(u, z_start):
        th = th0
        if theta_params:
            th = th.at[th_k, th_i].set(th_scale * u[n_design:])
        x, info = evaluate_design(design_of(u[:n_design]), w, th, z0=z_start)
        model = x[idx_k, idx_s] - jnp.where(is_delta, x[idx_ref, idx_s], 0.0)
        data = (model - values) / sigmas
        r = jnp.concatenate([data, prior_weight * u[:n_design]])
        return r, (info.converged, jax.lax.stop_gradient(info.z))

    residual.z0 = z0

    return residual, design_of


# The design fit's damping: a cautious start, slow to shrink (a design far from the
# data moves the balance a long way), and its stopping rule (relative cost decrease).
DESIGN_DAMPING = Damping(init=1e-2, shrink=3.0, grow=4.0, low=1e-9)
DESIGN_FTOL = 1e-7


def _solve(residual, u0, z0, *, max_iter: int, verbose: bool):
    """The core's Levenberg-Marquardt on ``residual(u, z_start) -> (r, (converged,
    z))`` with the Newton starts ``z`` as its hint; a non-converged solve makes the
    residual NaN (the trial is rejected)."""

    def hinted(u, z_start):
        r, (ok, z) = residual(u, z_start)
        return jnp.where(jnp.all(ok), r, jnp.nan), z

    tol = Tolerance(max_iters=max_iter, ftol=DESIGN_FTOL)

    def solve(u0, z0):
        return lm_solve(linearize(hinted, hinted=True), u0, tol, DESIGN_DAMPING,
                        hint=z0, verbose=verbose)  # fmt: skip

    return jax.jit(solve)(u0, z0)


def fit_design(
    base: EngineDesign,
    params: Sequence[FitParam],
    conditions: np.ndarray,
    thetas: np.ndarray,
    targets: Sequence[Target],
    *,
    theta_params: Sequence[ThetaParam] = (),
    prior_weight: float = 1.0,
    max_iter: int = 60,
    verbose: bool = False,
) -> FitResult:
    """Fit ``params`` of ``base`` to ``targets`` at ``conditions`` (see the module
    docstring)."""
    residual, design_of = make_residual_fn(
        base, params, conditions, thetas, targets, prior_weight, theta_params
    )
    u0 = jnp.zeros(len(params) + len(theta_params))
    state, stats = _solve(residual, u0, residual.z0, max_iter=max_iter, verbose=verbose)
    if int(stats.status) == -1:
        raise FloatingPointError("the engine does not converge at the nominal design")
    jac = np.asarray(state.jac)
    if not np.all(np.isfinite(jac)):
        raise FloatingPointError("non-finite Jacobian at the LM solution")
    # numpy.linalg.pinv's cut-off: the prior keeps the design block well posed
    cov = np.asarray(gauss_newton_cov(state.jac, rcond=1e-15))
    u = state.y
    design = jax.tree.map(np.asarray, design_of(u[: len(params)]))
    costs = np.asarray(stats.costs)[: int(stats.num_iters) + 1]
    return FitResult(
        design=design,
        u=np.asarray(u),
        cost_history=(2.0 * costs).tolist(),  # sum of squares, as reported
        residuals=np.asarray(state.resid[: len(targets)]),
        u_std=np.sqrt(np.clip(np.diag(cov), 0.0, None)),
        theta=np.asarray(u[len(params) :]) * np.array([t.scale for t in theta_params]),
    )
