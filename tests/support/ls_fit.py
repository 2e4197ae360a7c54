"""A constant ``theta`` fitted to a whole record by the library's LM core (tests only).

The reference the tests hold the streaming least squares, partial rows and padding
against: Levenberg–Marquardt (:mod:`jaxcal.numerics.levenberg_marquardt`) on
``0.5 * sum_t,s ((F(w_t, theta) - x_t) / noise_std)_s^2`` over valid rows and
observed outputs, iterated to a tolerance, with the covariance ``s^2 (J^T J)^-1``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.calibrators.interface import (
    MeasureFn,
    Measurement,
    check_measurement,
    check_scale,
)
from jaxcal.calibrators.methods.ls.window import damping_of
from jaxcal.numerics.levenberg_marquardt import (
    Tolerance,
    gauss_newton_cov,
    linearize,
    lm_solve,
)
from jaxcal.typedefs import Array


@dataclasses.dataclass(frozen=True)
class FitConfig(Tolerance):
    """Static settings of the batch fit: the solver's stopping rules (the fields of
    :class:`~jaxcal.numerics.levenberg_marquardt.Tolerance`, scipy-like, in scaled
    units) and its Marquardt damping."""

    damping_init: float = 1e-3  # initial Marquardt lambda
    damping_factor: float = 10.0  # lambda /= factor on acceptance, *= on rejection

    def __post_init__(self):
        super().__post_init__()
        if not (self.damping_init > 0 and self.damping_factor > 1):
            raise ValueError(
                "FitConfig: need damping_init > 0 and damping_factor > 1, got "
                f"{self.damping_init}, {self.damping_factor}"
            )


class FitInfo(NamedTuple):
    """Diagnostics of :func:`fit_least_squares` (``theta`` units where relevant)."""

    cost: Array  # [] 0.5 * sum of squared normalised residuals at the solution
    grad_norm: Array  # [] ||J^T r||_inf in scaled units
    num_iters: Array  # [] int, LM iterations taken
    cov: Array  # [P, P] s^2 (J^T J)^-1, s^2 = 2 cost / (num_residuals - P)
    theta_std: Array  # [P] sqrt(diag(cov))
    converged: Array  # [] bool, a tolerance was met with a finite cost


def fit_least_squares(
    measure_fn: MeasureFn,
    w: Array,
    x: Array,
    theta0: Array,
    cfg: FitConfig | None = None,
    mask: Array | None = None,
    *,
    measurement: Measurement | None = None,
    theta_scale: Array | None = None,
) -> tuple[Array, FitInfo]:
    """Fit one constant ``theta`` to a whole record (jitted; vmappable over records).

    Minimises ``0.5 * sum_t,s ((F(w_t, theta) - x_t) / noise_std)_s^2`` over valid
    rows and observed outputs (a NaN in ``x`` is missing and left out) with
    Levenberg–Marquardt in ``lax.while_loop``. ``measure_fn`` and ``cfg`` are static:
    reuse the same function object to avoid recompiling.

    Args:
        measure_fn: ``F(w [Wd], theta [P]) -> x [S]``.
        w: ``[T, Wd]``.
        x: ``[T, S]``.
        theta0: ``[P]`` starting point.
        cfg: tolerances and damping (default :class:`FitConfig`).
        mask: ``[T]`` validity or ``None``.
        measurement: residuals are divided by ``measurement.noise_std``; ``None``
            keeps raw units.
        theta_scale: ``[P]`` scales the iteration works in, or ``None``.

    Returns:
        ``(theta [P], FitInfo)``. The covariance estimates the noise from the fit
        (``s^2``), so it is meaningful for any residual unit.
    """
    cfg = FitConfig() if cfg is None else cfg
    w, x = jnp.asarray(w), jnp.asarray(x)
    if w.ndim != 2 or x.ndim != 2 or w.shape[0] != x.shape[0]:
        raise ValueError(
            f"fit_least_squares: expected w [T, Wd], x [T, S]; got {w.shape}, {x.shape}"
        )
    theta0 = jnp.asarray(theta0, dtype=jnp.result_type(float))
    if theta0.ndim != 1:
        raise ValueError(f"theta0 must be [P], got shape {theta0.shape}")
    scale = check_scale(theta_scale, theta0.shape[0], theta0.dtype)
    std = (
        jnp.ones(x.shape[1], theta0.dtype)
        if measurement is None
        else check_measurement(measurement).noise_std
    )
    if std.shape != (x.shape[1],):
        raise ValueError(
            f"measurement.noise_std must be [S] = ({x.shape[1]},), got {std.shape}"
        )
    mask = jnp.ones(w.shape[:1], bool) if mask is None else jnp.asarray(mask, bool)
    if mask.shape != w.shape[:1]:
        raise ValueError(f"mask must be [T] = {w.shape[:1]}, got {mask.shape}")
    return _fit_jit(measure_fn, cfg, w, x, theta0, mask, std, scale)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _fit_jit(measure_fn, cfg, w, x, theta0, mask, std, scale):
    w = jnp.where(mask[:, None], w, w[jnp.argmax(mask)])  # never evaluate padding
    used = mask[:, None] & ~jnp.isnan(x)  # [T, S] missing outputs leave the sum
    x = jnp.where(used, x, 0.0)

    def residual(z):
        pred = jax.vmap(lambda w_t: measure_fn(w_t, scale * z))(w)
        return jnp.where(used, (pred - x) / std, 0.0).ravel()

    fit, stats = lm_solve(linearize(residual), theta0 / scale, cfg, damping_of(cfg))
    num_resid = jnp.sum(used)
    num_params = theta0.shape[0]
    s2 = 2.0 * fit.cost / jnp.maximum(num_resid - num_params, 1)
    cov = gauss_newton_cov(fit.jac, s2=s2) * scale[:, None] * scale[None, :]
    info = FitInfo(
        cost=fit.cost,
        grad_norm=jnp.max(jnp.abs(fit.jac.T @ fit.resid)),
        num_iters=stats.num_iters,
        cov=cov,
        theta_std=jnp.sqrt(jnp.diagonal(cov)),
        converged=stats.status == 1,
    )
    return scale * fit.y, info
