"""Unscented Kalman filter over the calibrated parameters (the paper's UKF baseline).

State-space model of the paper (eq. ukf and appendix "Set-up of the UKF algorithm")::

    theta_t = theta_{t-1} + xi_t,        xi ~ N(0, Q),  Q = q^2 I
    x_t     = F(w_t, theta_t) + eps_t,   eps ~ N(0, R), R = r^2 I  (compared outputs)

filtered with the additive-noise UKF of Särkkä (2013), "Bayesian Filtering and
Smoothing", alg. 5.14 (sigma points and weights of its eqs. for the scaled unscented
transform). Choices the paper leaves open, fixed here:

* Outputs are compared as ``x_n = (x - centre) / noise_std``, the
  :class:`~jaxcal.calibrators.interface.Measurement`, so ``R = r^2 I`` there and
  ``R = diag((r noise_std)^2)`` in output units. The paper's methods take the
  training statistics (``noise_std`` the training std), so ``r`` is in units of each
  sensor's spread, as the appendix says; :func:`jaxcal.calibrate` passes the
  measurement noise std with ``r = 1`` (:mod:`jaxcal.calibrators.programs.compiled`).
* Parameters may be normalised too: the filter works in ``z = theta / theta_scale``
  (``theta_scale`` e.g. the training std of each parameter), so ``q`` and ``prior_std``
  are in those units. ``theta_scale=None`` means raw ``theta`` units. Outputs are
  always in ``theta`` units.
* Prediction with identity dynamics is computed in closed form (``m, P + Q``): the
  unscented transform of the identity is exact, so sigma points there would only cost.
  Each step therefore evaluates ``F`` at the ``K = 2P + 1`` sigma points (vmapped),
  plus one more at the posterior mean when ``posterior_xhat`` is on.
* Weights default to ``alpha=1, beta=2, kappa=0``: all weights positive and a spread
  of ``sqrt(P)`` standard deviations. Wan & van der Merwe's ``alpha=1e-3`` keeps
  sigma points local for strongly nonlinear models at the price of a large negative
  centre weight (cancellation; use float64 then).

Hidden states (Särkkä 2013, sec. 5.6 on augmented state-space models; the joint
filter of e.g. Wan & van der Merwe 2001): for a model with memory,
``(z_t, x_t) = step(z_{t-1}, w_t, theta_t)``, the filter's state is the augmented
``a = [z / state_scale, theta / theta_scale]``. One unscented transform per sample
propagates the sigma points of ``(z_{t-1}, theta_t)`` through ``step`` and gives the
predicted ``z_t``, the predicted ``x_t`` and their cross-covariances at once; the
parameter block keeps its exact identity prediction, process noise ``state_q`` is
added to ``z_t`` after the transform. A static model is the case ``Z = 0``
(:func:`make_ukf`): the same code, the same numbers.

Missing outputs: a NaN in ``x_t`` (a sensor channel dropped out) is a missing
measurement; the update uses the observed outputs only
(:func:`~jaxcal.calibrators.ukf_steps.update`), so the filter takes partial rows
(``Calibrator.accepts_partial``). ``xhat`` still holds every output (the model's
prediction of the missing ones).

The numerics of one step (settings, belief, the unscented transform, the update) are
in :mod:`jaxcal.calibrators.ukf_steps`; this module assembles them into the filter.

Float64 is recommended (covariance updates lose positive definiteness in float32 at
``q = r = 0.01``); the Cholesky factorisation adds ``jitter`` to the diagonal.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxcal.calibrators.gaussian_filter import (
    Moments,
    make_gaussian_filter,
    static_transition,
)
from jaxcal.calibrators.interface import (
    Calibrator,
    CalOutput,
    MeasureFn,
    Measurement,
    check_measurement,
    check_prior,
    run_calibrator,
    run_fleet,
)
from jaxcal.calibrators.ukf_steps import (  # noqa: F401 (re-exported: one import path)
    UKFConfig,
    joint_prior,
    predict,
    sigma_points,
    unscented_weights,
)
from jaxcal.problem import Transition
from jaxcal.typedefs import Array


def make_ukf(
    measure_fn: MeasureFn,
    cfg: UKFConfig,
    measurement: Measurement,
    *,
    theta0: Array,
    theta_scale: Array | None = None,
    theta_box: tuple[Array, Array] | None = None,
) -> Calibrator:
    """Build the paper's UKF as a :class:`~jaxcal.calibrators.interface.Calibrator`.

    Args:
        measure_fn: ``F(w [Wd], theta [P]) -> x [S]`` (declared parameters only; see
            ``Problem.measure()``). Must be jittable and vmappable over ``theta``.
        cfg: static settings.
        measurement: ``centre``/``noise_std`` ``[S]``: the outputs are compared as
            ``(x - centre) / noise_std``, with noise std ``cfg.r`` there (``R =
            diag((cfg.r noise_std)^2)``).
        theta0: ``[P]`` prior mean of the parameters (theta units).
        theta_scale: ``[P]`` positive scales; the filter runs in ``theta / scale``.
        theta_box: ``(low [P], high [P])``: the posterior mean is projected onto
            it after each update (the estimate projection of constrained Kalman
            filtering, Simon 2010, IET Control Theory Appl. 4(8)), a hair inside
            (``BOX_MARGIN`` of its width: a model singular at its bound stays
            finite), so the estimate stays inside the declared bounds; the sigma
            points are evaluated where
            they fall, the unscented transform undistorted (``None``: free).

    Returns:
        ``Calibrator(init, step)``; the state is :class:`UKFState`; ``step`` reports
        ``theta`` (posterior mean), ``xhat`` and ``aux`` with ``theta_std [P]``,
        ``innovation [S]`` (compared ``x_n - E[x_n]`` before the update; 0 on a
        missing output), ``innovation_std [S]`` (its predicted std, the root of
        ``diag S``), ``log_likelihood []`` (of the compared observed outputs of
        ``x_t`` given the past) and, if asked, ``theta_cov [P, P]``. ``x_t`` may
        hold NaN in some outputs (missing): the update uses the observed ones.
    """
    return make_joint_ukf(
        static_transition(measure_fn), cfg, measurement, theta0=theta0,
        theta_scale=theta_scale, theta_box=theta_box, clip_points=False,
    )  # fmt: skip


def unscented(cfg: UKFConfig) -> Moments:
    """The UKF's moments: the scaled unscented transform of the prediction and of
    the prior of a model with memory (:mod:`jaxcal.calibrators.ukf_steps`)."""
    return Moments(
        predict=lambda state, propagate, noise, weights, num_states: predict(
            state, propagate, noise, weights, cfg, num_states
        ),
        prior=lambda at_rest, u0, cov_u, s_std, s_scale: joint_prior(
            at_rest, u0, cov_u, cfg, s_std, s_scale
        ),
        weights=lambda n, dtype: unscented_weights(n, cfg),
    )


def make_joint_ukf(
    transition: Transition,
    cfg: UKFConfig,
    measurement: Measurement,
    *,
    theta0: Array,
    theta_scale: Array | None = None,
    state_std: Array | None = None,
    state_q: Array | None = None,
    state_scale: Array | None = None,
    theta_box: tuple[Array, Array] | None = None,
    clip_points: bool = True,
) -> Calibrator:
    """The joint (augmented) state-and-parameter UKF of a model with memory.

    Args:
        transition: ``Transition(init, step, Z)`` (``Problem.transition()``):
            ``init(w0 [Wd], theta [P]) -> z0 [Z]`` is the prior mean of the state
            before the first sample, ``step(z [Z], w [Wd], theta [P]) -> (z', x
            [S])``; with ``Z = 0`` this is the static filter of :func:`make_ukf`.
        cfg, measurement, theta0, theta_scale: as in :func:`make_ukf`.
        state_std: ``[Z]`` std of the initial state around ``init_state`` (state
            units; 0 = known exactly). Default: ``state_scale``.
        state_q: ``[Z]`` process-noise std added to the state per step (model error
            in the state equation; default 0, the model is trusted).
        state_scale: ``[Z]`` positive natural size of each state (the filter works
            in ``z / state_scale``); default ones.
        theta_box: ``(low [P], high [P])``: the model is evaluated at each sigma
            point's parameters clipped into this box. Sigma points spread
            ``sqrt(Z + P)`` standard deviations; with a broad prior they leave the
            range where a dynamic model is stable (a time constant below zero),
            and one non-finite point stalls the filter for good. The posterior
            mean's parameters are projected onto the box after each update (see
            :func:`make_ukf`).
        clip_points: clip the sigma points' parameters into ``theta_box`` (False:
            only the posterior mean is projected; :func:`make_ukf`).

    Returns:
        ``Calibrator(init, step)`` as :func:`make_ukf`, with ``aux["state"] [Z]`` and
        ``aux["state_std"] [Z]`` (the filtered state after the sample) when ``Z > 0``.
        The filter's skeleton is :func:`~jaxcal.calibrators.gaussian_filter.
        make_gaussian_filter`, shared with the EKF.
    """
    return make_gaussian_filter(
        unscented(cfg), transition, cfg, measurement, theta0=theta0,
        theta_scale=theta_scale, state_std=state_std, state_q=state_q,
        state_scale=state_scale, theta_box=theta_box, clip_points=clip_points,
    )  # fmt: skip


def ukf_filter(
    measure_fn: MeasureFn,
    w: Array,
    x: Array,
    measurement: Measurement,
    cfg: UKFConfig | None = None,
    *,
    theta0: Array,
    theta_scale: Array | None = None,
    mask: Array | None = None,
    unroll: int = 1,
) -> CalOutput:
    """Jitted entry point: the UKF over one record or a fleet.

    ``measure_fn`` and ``cfg`` are static arguments of the jitted function: pass the
    same function object on every call, or each call recompiles.

    Args:
        measure_fn: ``F(w [Wd], theta [P]) -> x [S]``.
        w: ``[T, Wd]`` or a fleet ``[U, T, Wd]``.
        x: ``[T, S]`` or ``[U, T, S]``.
        measurement: the outputs' ``centre`` and ``noise_std`` ``[S]``
            (:func:`make_ukf`).
        cfg: settings (default :class:`UKFConfig`, the paper's q = r = 0.01).
        theta0: ``[P]`` prior mean. theta_scale: ``[P]`` or ``None``.
        mask: ``[T]`` / ``[U, T]`` validity, ``None`` for all valid.
        unroll: ``lax.scan`` unroll factor.

    Returns:
        ``CalOutput`` (``theta [.., T, P]``, ``xhat [.., T, S]``, ``aux``; see
        :func:`make_ukf`).
    """
    cfg = UKFConfig() if cfg is None else cfg
    measurement = check_measurement(measurement)
    w, x = jnp.asarray(w), jnp.asarray(x)
    if w.ndim not in (2, 3) or x.ndim != w.ndim:
        raise ValueError(f"w, x must be [T, .] or [U, T, .]; got {w.shape}, {x.shape}")
    if x.shape[-1] != measurement.centre.shape[0]:
        raise ValueError(
            f"x has {x.shape[-1]} sensors but measurement has "
            f"{measurement.centre.shape[0]}"
        )
    theta0, _ = check_prior(theta0, theta_scale)
    return _ukf_filter_jit(
        measure_fn, cfg, unroll, w, x, measurement, theta0, theta_scale, mask
    )


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _ukf_filter_jit(
    measure_fn, cfg, unroll, w, x, measurement, theta0, theta_scale, mask
):
    ukf = make_ukf(measure_fn, cfg, measurement, theta0=theta0, theta_scale=theta_scale)
    if w.ndim == 3:
        return run_fleet(ukf, w, x, mask, unroll=unroll)
    return run_calibrator(ukf, w, x, mask, unroll=unroll)
