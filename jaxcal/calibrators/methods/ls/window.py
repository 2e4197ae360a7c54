"""Levenberg–Marquardt least squares on a differentiable model, streaming.

One damped Gauss–Newton iteration (Levenberg 1944, Marquardt 1963; Nocedal & Wright
2006, sec. 10.3), working in scaled parameters ``z = theta / theta_scale`` on
residuals in units of each output's noise std (the
:class:`~jaxcal.calibrators.interface.Measurement`'s ``noise_std``, times the config's
``r``). :func:`make_least_squares` is a streaming calibrator (the interface of
:mod:`jaxcal.calibrators.interface`). Its state is a ring buffer of the last
``window`` samples; each step inserts the new sample and runs ``num_iters`` LM
iterations on ``sum_i ||(F(w_i, theta) - x_i) / (noise_std r)||^2
[+ ||(z - z_prev) / prior_std||^2]``, warm-started from the previous estimate
``z_prev``. The optional Gaussian prior (a Tikhonov term towards ``z_prev``) steadies
poorly observed directions.

The iteration, its damping (Marquardt's ``lambda diag(J^T J)``, adapted by factors on
acceptance / rejection; a trial point with a non-finite cost is rejected, so a failed
model evaluation never enters θ) and the covariance are the one solver core's,
:mod:`jaxcal.numerics.levenberg_marquardt`. Jacobians come from ``jax.jacfwd`` over
the ``P`` declared parameters, so an iteration costs one model evaluation per sample
plus ``P`` tangent sweeps (cheap linear solves for an implicit-function model like
the engine). A streaming step costs ``window * (num_iters + 1)`` such evaluations.

Missing outputs: a NaN in ``x`` (a sensor channel dropped out) is left out of the
sum of squares (a masked residual, fixed shapes), so it takes partial rows
(``Calibrator.accepts_partial``).

The streaming std is :func:`~jaxcal.calibrators.uncertainty.drift_std.drift_std`: honest
when theta drifts within the window (``aux["laplace_std"]`` keeps the fit's own std).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

from jaxcal.calibrators.interface import (
    Calibrator,
    CalStepOutput,
    MeasureFn,
    Measurement,
    check_measurement,
    check_prior,
    inner_box,
)
from jaxcal.calibrators.uncertainty.drift_std import (
    DriftHistory,
    drift_std,
    init_drift_history,
    prior_age,
)
from jaxcal.numerics.levenberg_marquardt import (
    Damping,
    gauss_newton_cov,
    linearize,
    lm_run,
)
from jaxcal.typedefs import Array, PRNGKey


@dataclasses.dataclass(frozen=True)
class LeastSquaresConfig:
    """Static settings of the sliding-window calibrator."""

    window: int = 32  # samples in the sliding window (ring buffer length)
    num_iters: int = 3  # LM iterations per step (fixed cost per sample)
    r: float = 0.01  # noise std in units of Measurement.noise_std (weighs the prior)
    prior_std: float | None = None  # prior std around the previous z; None: no prior
    damping_init: float = 1e-3  # Marquardt lambda at the start of every step
    damping_factor: float = 10.0  # lambda /= factor on acceptance, *= on rejection

    def __post_init__(self):
        if self.window < 1 or self.num_iters < 1:
            raise ValueError(
                "LeastSquaresConfig.window and .num_iters must be >= 1, "
                f"got {self.window}, {self.num_iters}"
            )
        if not (self.r > 0 and self.damping_init > 0 and self.damping_factor > 1):
            raise ValueError(
                "LeastSquaresConfig: need r > 0, damping_init > 0 and "
                "damping_factor > 1"
            )
        if self.prior_std is not None and not self.prior_std > 0:
            raise ValueError(
                f"LeastSquaresConfig.prior_std must be > 0 or None, "
                f"got {self.prior_std}"
            )


@struct.dataclass
class LSState:
    """Sliding-window state: estimate plus the last ``window`` samples."""

    z: Array  # [P] scaled estimate theta / theta_scale
    w_buf: Array  # [N, Wd]
    x_buf: Array  # [N, S] (0 where an output was missing: the state stays finite)
    observed: Array  # [N, S] bool, False where an output was missing (NaN)
    valid: Array  # [N] bool, False until a slot has been filled
    pos: Array  # [] int32, next slot to overwrite
    history: DriftHistory  # the past estimates the drift is measured from


def damping_of(cfg) -> Damping:
    """The core's damping schedule of a config (lambda divided / multiplied by
    ``damping_factor`` on acceptance / rejection)."""
    return Damping(cfg.damping_init, cfg.damping_factor, cfg.damping_factor)


def make_least_squares(
    measure_fn: MeasureFn,
    cfg: LeastSquaresConfig,
    measurement: Measurement,
    *,
    theta0: Array,
    theta_scale: Array | None = None,
    theta_box: tuple[Array, Array] | None = None,
) -> Calibrator:
    """Sliding-window Levenberg–Marquardt calibrator.

    Args:
        measure_fn: ``F(w [Wd], theta [P]) -> x [S]``, differentiable in ``theta``.
        cfg: static settings.
        measurement: the outputs' ``noise_std [S]`` (times ``cfg.r``) is the
            residual unit; ``centre`` is not used (residuals are differences).
        theta0: ``[P]`` initial estimate (theta units).
        theta_scale: ``[P]`` positive scales of theta, or ``None``.
        theta_box: ``(low [P], high [P])``: each LM step's point is projected
            onto it, a hair inside (:func:`~jaxcal.calibrators.interface.
            inner_box`), so the estimate stays inside the declared bounds
            (``None``: free; :func:`~jaxcal.numerics.levenberg_marquardt.
            lm_iterate`).

    Returns:
        ``Calibrator(init, step)`` with :class:`LSState`; ``step`` takes ``x_t`` with
        NaN on missing outputs (left out of the residual) and reports ``theta``,
        ``xhat = F(w_t, theta_t)`` (from the cached residual, no extra evaluation
        unless an output is missing) and
        ``aux`` with ``theta_std [P]`` (the Laplace std ``(J^T J)^-1`` with noise
        ``r``, widened by the window's lag behind a drifting theta: see
        :func:`drift_std`), ``laplace_std [P]`` (the fit's alone) and ``cost []``.
    """
    measurement = check_measurement(measurement)
    theta0, scale = check_prior(theta0, theta_scale)
    sigma = measurement.noise_std * cfg.r  # residual unit: one noise std
    box = inner_box(theta_box, scale)

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> LSState:
        del key
        return _initial_state(cfg.window, theta0, scale, w0, x0)

    def step(state: LSState, w_t: Array, x_t: Array) -> tuple[LSState, CalStepOutput]:
        observed_t = ~jnp.isnan(x_t)  # a missing output leaves the residual
        filled = _insert(state, w_t, x_t, observed_t)
        z_prev = state.z
        used = filled.valid[:, None] & filled.observed  # [N, S] the cost's residuals

        def residual(z):
            pred = jax.vmap(lambda w: measure_fn(w, scale * z))(filled.w_buf)
            r = jnp.where(used, (pred - filled.x_buf) / sigma, 0.0).ravel()
            if cfg.prior_std is not None:
                r = jnp.concatenate([r, (z - z_prev) / cfg.prior_std])
            return r

        fit = lm_run(
            linearize(residual), z_prev, cfg.num_iters, damping_of(cfg), box=box
        )
        num_sensors = x_t.shape[0]
        r_now = lax.dynamic_slice(fit.resid, (state.pos * num_sensors,), (num_sensors,))
        std, laplace_std, history = _lagged_std(fit, state, cfg, num_sensors)
        aux = {
            "theta_std": scale * std,
            "laplace_std": scale * laplace_std,
            "cost": fit.cost,
        }
        new_state = filled.replace(
            z=fit.y, pos=(state.pos + 1) % cfg.window, history=history
        )
        # F(w_t, theta) from the cached residual; a missing output has none there
        # (masked to 0), so a partial row costs one model evaluation more.
        from_resid = x_t + sigma * r_now
        xhat = lax.cond(
            jnp.all(observed_t),
            lambda: from_resid,
            lambda: measure_fn(w_t, scale * fit.y).astype(from_resid.dtype),
        )
        out = CalStepOutput(theta=scale * fit.y, xhat=xhat, aux=aux)
        return new_state, out

    return Calibrator(init=init, step=step, accepts_partial=True)


def _initial_state(window: int, theta0, scale, w0: Array, x0: Array) -> LSState:
    """The state before the first sample: the estimate at ``theta0``; unfilled slots
    hold the first sample so the model is never run at zeros."""
    return LSState(
        z=theta0 / scale,
        w_buf=jnp.tile(w0, (window, 1)),
        x_buf=jnp.tile(jnp.nan_to_num(x0), (window, 1)),
        observed=jnp.ones((window, x0.shape[0]), bool),
        valid=jnp.zeros((window,), bool),
        pos=jnp.zeros((), jnp.int32),
        history=init_drift_history(theta0 / scale, window),
    )


def _insert(state: LSState, w_t: Array, x_t: Array, observed_t: Array) -> LSState:
    """``state`` with the sample written into the ring buffer's slot ``pos`` (a
    missing output as 0, marked not ``observed``); ``pos`` not advanced yet."""
    return state.replace(
        w_buf=state.w_buf.at[state.pos].set(w_t),
        x_buf=state.x_buf.at[state.pos].set(jnp.where(observed_t, x_t, 0.0)),
        observed=state.observed.at[state.pos].set(observed_t),
        valid=state.valid.at[state.pos].set(True),
    )


def _lagged_std(fit, state: LSState, cfg: LeastSquaresConfig, num_sensors: int):
    """``(std, laplace_std, history)`` (:func:`drift_std`) of the window's fit: each
    residual row's sample age (slot ``pos`` is the newest; the prior on ``z`` is
    pseudo-data of the previous estimate's age) sets its response to a drift."""
    cov = gauss_newton_cov(fit.jac)
    ages = (state.pos - jnp.arange(cfg.window)) % cfg.window  # slot -> age
    ages = jnp.repeat(ages.astype(cov.dtype), num_sensors)
    if cfg.prior_std is not None:
        ages = jnp.concatenate([ages, prior_age(state.history)])
    drift_jac = -ages[:, None] * fit.jac
    if cfg.prior_std is not None:
        ages = ages.at[-fit.y.shape[0] :].set(-1.0)  # the prior: no sample
    return drift_std(state.history, fit.y, cov, fit.jac, drift_jac, ages, cfg.window)
