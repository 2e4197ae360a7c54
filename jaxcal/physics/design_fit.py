"""Fitting design constants to measured operating points (a calibration problem itself).

The unknowns are a chosen subset of :class:`EngineDesign` fields, written as
``value = nominal + scale * u`` with a standard-normal prior on ``u`` (the prior keeps
constants the data do not determine at their textbook values, physics_facts.md). The data
residuals are ``(x(w_k; design) - target)/sigma``. Levenberg-Marquardt on the stacked
residual vector uses the exact Jacobian ``jax.jacfwd`` through the implicit-function
gradients of the Newton solve (no finite differences).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.physics.configs import design_from_flat, design_to_flat
from jaxcal.physics.constants import SENSOR_NAMES
from jaxcal.physics.design import (
    EngineDesign,
    corrected_fan_speed_demand,
    design_point,
)
from jaxcal.physics.evaluation import evaluate_design
from jaxcal.physics.guess import build_guess_table, initial_guess


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
    z0 = jax.vmap(initial_guess, (None, 0, 0))(table, pcn, jnp.asarray(conditions)[:, 1])
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


def levenberg_marquardt(residual, u0, z0, *, max_iter=60, tol=1e-10, verbose=False):
    """Host-loop LM with jitted residual and Jacobian (a few dozen iterations).

    ``residual(u, z_start) -> (r, (converged, z))``; every evaluation starts the engine's
    Newton solves from the solutions of the last accepted step, so the balance stays on
    its physical branch while the design moves (continuation in design space).
    """
    r_fn = jax.jit(residual)
    j_fn = jax.jit(jax.jacfwd(lambda u, z: residual(u, z)[0]))
    u = jnp.asarray(u0)
    r, (ok, z) = r_fn(u, z0)
    if not bool(jnp.all(ok)):
        raise FloatingPointError("the engine does not converge at the nominal design")
    cost = float(jnp.sum(r**2))
    lam = 1e-2
    history = [cost]
    for it in range(max_iter):
        jac = j_fn(u, z)
        jtj, g = jac.T @ jac, jac.T @ r
        improved = False
        for _ in range(12):
            step = -jnp.linalg.solve(jtj + lam * jnp.diag(jnp.diag(jtj) + 1e-9), g)
            r_new, (ok_new, z_new) = r_fn(u + step, z)
            c_new = float(jnp.sum(r_new**2))
            if bool(jnp.all(ok_new)) and np.isfinite(c_new) and c_new < cost:
                u, r, z, cost, improved = u + step, r_new, z_new, c_new, True
                lam = max(lam / 3.0, 1e-9)
                break
            lam *= 4.0
        history.append(cost)
        if verbose:
            print(f"LM {it:3d} cost {cost:.6g} lambda {lam:.2g}", flush=True)
        if not improved or (history[-2] - cost) < max(tol, 1e-7) * max(cost, 1.0):
            break
    jac = np.asarray(j_fn(u, z))
    if not np.all(np.isfinite(jac)):
        raise FloatingPointError("non-finite Jacobian at the LM solution")
    cov = np.linalg.pinv(jac.T @ jac)
    return u, history, np.sqrt(np.clip(np.diag(cov), 0.0, None)), z


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
    """Fit ``params`` of ``base`` to ``targets`` at ``conditions`` (see module docstring)."""
    residual, design_of = make_residual_fn(
        base, params, conditions, thetas, targets, prior_weight, theta_params
    )
    u0 = jnp.zeros(len(params) + len(theta_params))
    u, history, u_std, z = levenberg_marquardt(
        residual, u0, residual.z0, max_iter=max_iter, verbose=verbose
    )
    r, _ = jax.jit(residual)(u, z)
    design = jax.tree.map(np.asarray, design_of(u[: len(params)]))
    return FitResult(
        design=design,
        u=np.asarray(u),
        cost_history=history,
        residuals=np.asarray(r[: len(targets)]),
        u_std=u_std,
        theta=np.asarray(u[len(params) :])
        * np.array([t.scale for t in theta_params]),
    )
