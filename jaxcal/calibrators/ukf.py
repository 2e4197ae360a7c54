"""Unscented Kalman filter over the calibrated parameters (the paper's UKF baseline).

State-space model of the paper (eq. ukf and appendix "Set-up of the UKF algorithm")::

    theta_t = theta_{t-1} + xi_t,        xi ~ N(0, Q),  Q = q^2 I
    x_t     = F(w_t, theta_t) + eps_t,   eps ~ N(0, R), R = r^2 I  (normalised outputs)

filtered with the additive-noise UKF of Särkkä (2013), "Bayesian Filtering and
Smoothing", alg. 5.14 (sigma points and weights of its eqs. for the scaled unscented
transform). Choices the paper leaves open, fixed here:

* Outputs are normalised, ``x_n = (x - mean) / std`` with the training statistics, so
  ``r`` is in units of each sensor's spread, as the appendix says.
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
measurement; the update uses the observed outputs only (:func:`_observed_only`), so
the filter takes partial rows (``Calibrator.accepts_partial``). ``xhat`` still holds
every output (the model's prediction of the missing ones).

Float64 is recommended (covariance updates lose positive definiteness in float32 at
``q = r = 0.01``); the Cholesky factorisation adds ``jitter`` to the diagonal.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.scipy.linalg import cho_factor, cho_solve

from jaxcal.calibrators.interface import (
    Calibrator,
    CalOutput,
    CalStepOutput,
    MeasureFn,
    SensorNorm,
    check_norm,
    check_prior,
    check_scale,
    run_calibrator,
    run_fleet,
)
from jaxcal.problem import Transition
from jaxcal.typedefs import Array, PRNGKey


@dataclasses.dataclass(frozen=True)
class UKFConfig:
    """Static UKF settings (hashable, closed over by :func:`make_ukf`)."""

    q: float = 0.01  # random-walk std per step, scaled-theta units (paper: 0.01)
    r: float = 0.01  # measurement noise std, normalised-sensor units (paper: 0.01)
    prior_std: float = 1.0  # std of theta_0 around theta0, scaled-theta units
    alpha: float = 1.0  # sigma-point spread (scaled unscented transform)
    beta: float = 2.0  # prior-knowledge weight on the centre point (2: Gaussian)
    kappa: float = 0.0  # secondary spread parameter
    jitter: float = 1e-10  # added to the covariance diagonal before Cholesky
    posterior_xhat: bool = True  # xhat = F(w, theta_post): one extra evaluation
    return_cov: bool = False  # also report aux["theta_cov"] [P, P]

    def __post_init__(self):
        for name in ("q", "r", "prior_std", "alpha"):
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"UKFConfig.{name} must be > 0, got {getattr(self, name)}"
                )
        if not self.jitter >= 0:
            raise ValueError(f"UKFConfig.jitter must be >= 0, got {self.jitter}")


@struct.dataclass
class UKFState:
    """Gaussian belief over the scaled augmented state
    ``[z / state_scale, theta / theta_scale]`` (``[P]`` for a static model)."""

    mean: Array  # [Z + P]
    cov: Array  # [Z + P, Z + P]


def unscented_weights(num_params: int, cfg: UKFConfig) -> tuple[Array, Array, float]:
    """Mean and covariance weights of the scaled unscented transform.

    Särkkä (2013), alg. 5.14: ``lambda = alpha^2 (n + kappa) - n``,
    ``Wm_0 = lambda / (n + lambda)``, ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``,
    ``Wm_i = Wc_i = 1 / (2 (n + lambda))``.

    Args:
        num_params: state dimension ``n = P``.
        cfg: the UKF configuration.

    Returns:
        ``(wm [K], wc [K], c)`` with ``K = 2P + 1`` and ``c = sqrt(n + lambda)`` the
        sigma-point spread.
    """
    n = num_params
    lambda_ = cfg.alpha**2 * (n + cfg.kappa) - n
    if not n + lambda_ > 0:
        raise ValueError(
            f"UKFConfig: need P + lambda > 0, got alpha={cfg.alpha}, "
            f"kappa={cfg.kappa} for P={n}"
        )
    wm = jnp.full((2 * n + 1,), 0.5 / (n + lambda_)).at[0].set(lambda_ / (n + lambda_))
    wc = wm.at[0].add(1.0 - cfg.alpha**2 + cfg.beta)
    return wm, wc, math.sqrt(n + lambda_)


def sigma_points(mean: Array, cov: Array, spread: float, jitter: float) -> Array:
    """The ``2P + 1`` sigma points ``[m, m + c L, m - c L]`` as one array expression.

    Args:
        mean: ``[P]``.
        cov: ``[P, P]``, symmetric positive (semi-)definite.
        spread: ``c = sqrt(P + lambda)``.
        jitter: added to the diagonal before the Cholesky factorisation.

    Returns:
        ``[K, P]`` points; row ``i + 1`` / ``P + i + 1`` uses column ``i`` of ``L``.
    """
    n = mean.shape[0]
    chol = jnp.linalg.cholesky(cov + jitter * jnp.eye(n, dtype=cov.dtype))
    offsets = spread * jnp.concatenate([jnp.zeros((1, n), cov.dtype), chol.T, -chol.T])
    return mean[None, :] + offsets


def make_ukf(
    measure_fn: MeasureFn,
    cfg: UKFConfig,
    norm: SensorNorm,
    *,
    theta0: Array,
    theta_scale: Array | None = None,
) -> Calibrator:
    """Build the paper's UKF as a :class:`~jaxcal.calibrators.interface.Calibrator`.

    Args:
        measure_fn: ``F(w [Wd], theta [P]) -> x [S]`` (declared parameters only; see
            ``measure_declared``). Must be jittable and vmappable over ``theta``.
        cfg: static settings.
        norm: sensor normalisation, ``mean``/``std`` ``[S]``.
        theta0: ``[P]`` prior mean of the parameters (theta units).
        theta_scale: ``[P]`` positive scales; the filter runs in ``theta / scale``.

    Returns:
        ``Calibrator(init, step)``; the state is :class:`UKFState`; ``step`` reports
        ``theta`` (posterior mean), ``xhat`` and ``aux`` with ``theta_std [P]``,
        ``innovation [S]`` (normalised ``x_n - E[x_n]`` before the update; 0 on a
        missing output), ``innovation_std [S]`` (its predicted std, the root of
        ``diag S``), ``log_likelihood []`` (of the normalised observed outputs of
        ``x_t`` given the past) and, if asked, ``theta_cov [P, P]``. ``x_t`` may
        hold NaN in some outputs (missing): the update uses the observed ones.
    """

    def init_state(w0, theta):
        del w0
        return jnp.zeros((0,), theta.dtype)

    def step(z, w, theta):
        return z, measure_fn(w, theta)

    return make_joint_ukf(
        Transition(init_state, step, 0), cfg, norm, theta0=theta0,
        theta_scale=theta_scale,
    )  # fmt: skip


def make_joint_ukf(
    transition: Transition,
    cfg: UKFConfig,
    norm: SensorNorm,
    *,
    theta0: Array,
    theta_scale: Array | None = None,
    state_std: Array | None = None,
    state_q: Array | None = None,
    state_scale: Array | None = None,
    theta_box: tuple[Array, Array] | None = None,
) -> Calibrator:
    """The joint (augmented) state-and-parameter UKF of a model with memory.

    Args:
        transition: ``Transition(init, step, Z)`` (``Problem.transition()``):
            ``init(w0 [Wd], theta [P]) -> z0 [Z]`` is the prior mean of the state
            before the first sample, ``step(z [Z], w [Wd], theta [P]) -> (z', x
            [S])``; with ``Z = 0`` this is the static filter of :func:`make_ukf`.
        cfg, norm, theta0, theta_scale: as in :func:`make_ukf`.
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
            and one non-finite point stalls the filter for good.

    Returns:
        ``Calibrator(init, step)`` as :func:`make_ukf`, with ``aux["state"] [Z]`` and
        ``aux["state_std"] [Z]`` (the filtered state after the sample) when ``Z > 0``.
    """
    norm = check_norm(norm)
    theta0, scale = check_prior(theta0, theta_scale)
    num_params = theta0.shape[0]
    init_state, step_fn, num_states = transition
    s_scale = check_scale(state_scale, num_states, theta0.dtype)
    s_std = _state_vector(state_std, num_states, s_scale, "state_std")
    s_q = _state_vector(state_q, num_states, 0.0 * s_scale, "state_q")
    n = num_states + num_params
    wm, wc, spread = unscented_weights(n, cfg)

    eye = jnp.eye(num_params, dtype=theta0.dtype)
    # Process noise: q on the parameters before the transform (theta_t = theta_{t-1}
    # + xi_t enters x_t), state_q on z_t after it (it enters x_{t+1}).
    q_theta = (
        jnp.zeros((n, n), theta0.dtype).at[num_states:, num_states:].set(cfg.q**2 * eye)
    )
    q_state = jnp.diag(
        jnp.concatenate([(s_q / s_scale) ** 2, jnp.zeros((num_params,), theta0.dtype)])
    )

    def unpack(a):
        return s_scale * a[:num_states], scale * a[num_states:]

    if theta_box is None:
        admissible = lambda theta: theta  # noqa: E731
    else:
        low, high = (jnp.asarray(b, theta0.dtype) for b in theta_box)
        admissible = lambda theta: jnp.clip(theta, low, high)  # noqa: E731

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> UKFState:
        del key, x0  # the prior is fixed by the factory
        u0 = theta0 / scale
        cov_u = cfg.prior_std**2 * eye
        if not num_states:
            return UKFState(mean=u0, cov=cov_u)
        # The initial state depends on the unknown parameters (a cell at rest:
        # z0 = init(w0, theta)): its prior is the unscented transform of init over
        # the parameter prior, cross-covariance included, plus state_std.
        wm_p, wc_p, spread_p = unscented_weights(num_params, cfg)
        points = sigma_points(u0, cov_u, spread_p, cfg.jitter)  # [2P + 1, P]
        z_points = (
            jax.vmap(
                lambda u: jnp.asarray(init_state(w0, admissible(scale * u)), u0.dtype)
            )(points)
            / s_scale
        )
        z_mean = wm_p @ z_points
        dz, du = z_points - z_mean, points - u0
        cov_zz = dz.T @ (wc_p[:, None] * dz) + jnp.diag((s_std / s_scale) ** 2)
        cov_zu = dz.T @ (wc_p[:, None] * du)
        cov = jnp.block([[cov_zz, cov_zu], [cov_zu.T, cov_u]])
        return UKFState(mean=jnp.concatenate([z_mean, u0]), cov=cov)

    def step(state: UKFState, w_t: Array, x_t: Array) -> tuple[UKFState, CalStepOutput]:
        def propagate(a: Array):
            z, theta = unpack(a)
            z_next, x = step_fn(z, w_t, admissible(theta))
            return z_next / s_scale, (x - norm.mean) / norm.std

        # One unscented transform of (z_{t-1}, theta_t) through the step.
        mean_prior = state.mean
        cov_prior = state.cov + q_theta
        points = sigma_points(mean_prior, cov_prior, spread, cfg.jitter)  # [K, n]
        z_points, y_points = jax.vmap(propagate)(points)  # [K, Z], [K, S]
        # The parameter block is carried unchanged: its prediction stays exact.
        mean_pred = jnp.concatenate([wm @ z_points, mean_prior[num_states:]])
        da = (
            jnp.concatenate([z_points, points[:, num_states:]], axis=1) - mean_pred
        )  # [K, n]
        y_mean = wm @ y_points
        dy = y_points - y_mean
        if num_states:
            cov_pred = da.T @ (wc[:, None] * da) + q_state
            cov_pred = cov_pred.at[num_states:, num_states:].set(
                cov_prior[num_states:, num_states:]
            )
        else:
            cov_pred = cov_prior
        eye_s = jnp.eye(dy.shape[1], dtype=dy.dtype)
        s_cov = dy.T @ (wc[:, None] * dy) + cfg.r**2 * eye_s
        cross = da.T @ (wc[:, None] * dy)  # [n, S]
        s_cov, cross, innovation = _observed_only(
            x_t, s_cov, cross, (x_t - norm.mean) / norm.std - y_mean, eye_s
        )
        s_chol = cho_factor(s_cov, lower=True)
        gain = cho_solve(s_chol, cross.T).T  # C S^-1
        mean = mean_pred + gain @ innovation
        cov = cov_pred - gain @ s_cov @ gain.T
        cov = 0.5 * (cov + cov.T)  # keep symmetric against round-off
        log_likelihood = -0.5 * (
            innovation @ cho_solve(s_chol, innovation)
            + 2.0 * jnp.sum(jnp.log(jnp.diag(s_chol[0])))
            + innovation.shape[0] * math.log(2.0 * math.pi)
            - jnp.sum(jnp.isnan(x_t)) * math.log(2.0 * math.pi)  # observed only
        )
        z_post, theta_post = unpack(mean)
        if cfg.posterior_xhat:  # x_t of the previous posterior state, new theta
            xhat = step_fn(unpack(state.mean)[0], w_t, admissible(theta_post))[1]
        else:  # the predicted measurement mean, free but one step behind the update
            xhat = norm.mean + norm.std * y_mean
        std = jnp.sqrt(jnp.clip(jnp.diag(cov), 0.0))
        aux = {
            "theta_std": scale * std[num_states:],
            "innovation": innovation,
            "innovation_std": jnp.sqrt(jnp.diag(s_cov)),  # its predicted std
            "log_likelihood": log_likelihood,
        }
        if num_states:
            aux["state"] = z_post
            aux["state_std"] = s_scale * std[:num_states]
        if cfg.return_cov:
            block = cov[num_states:, num_states:]
            aux["theta_cov"] = block * scale[:, None] * scale[None, :]
        new_state = UKFState(mean=mean, cov=cov)
        return new_state, CalStepOutput(theta=theta_post, xhat=xhat, aux=aux)

    return Calibrator(init=init, step=step, accepts_partial=True)


def _observed_only(
    x_t: Array, s_cov: Array, cross: Array, innovation: Array, eye_s: Array
) -> tuple[Array, Array, Array]:
    """The update on the observed outputs of ``x_t [S]`` (NaN: missing), in fixed
    shapes: the innovation is zeroed and the innovation covariance ``s_cov [S, S]``
    gets an identity block with zero cross-covariance (in ``s_cov`` and in ``cross
    [n, S]``) on the missing outputs. ``S`` is then block diagonal, the gain's
    columns of the missing outputs are zero, and mean, covariance and the log-det
    part of the likelihood are exactly those of the update on the observed subset
    (the standard treatment of missing measurements, e.g. Shumway & Stoffer 2017,
    sec. 6.4). A complete row is returned unchanged."""
    observed = ~jnp.isnan(x_t)
    both = observed[:, None] & observed[None, :]
    s_cov = jnp.where(both, s_cov, eye_s)
    cross = jnp.where(observed[None, :], cross, 0.0)
    return s_cov, cross, jnp.where(observed, innovation, 0.0)


def _state_vector(value, num_states: int, default: Array, field: str) -> Array:
    """A scalar or ``[Z]`` non-negative setting -> ``[Z]`` (``default`` if None)."""
    if value is None:
        return default
    arr = jnp.broadcast_to(jnp.asarray(value, default.dtype), (num_states,))
    if not isinstance(arr, jax.core.Tracer) and not np.all(np.asarray(arr) >= 0):
        raise ValueError(f"{field} must be >= 0 (scalar or [Z]), got {value}")
    return arr


def ukf_filter(
    measure_fn: MeasureFn,
    w: Array,
    x: Array,
    norm: SensorNorm,
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
        norm: sensor normalisation ``[S]``.
        cfg: settings (default :class:`UKFConfig`, the paper's q = r = 0.01).
        theta0: ``[P]`` prior mean. theta_scale: ``[P]`` or ``None``.
        mask: ``[T]`` / ``[U, T]`` validity, ``None`` for all valid.
        unroll: ``lax.scan`` unroll factor.

    Returns:
        ``CalOutput`` (``theta [.., T, P]``, ``xhat [.., T, S]``, ``aux``; see
        :func:`make_ukf`).
    """
    cfg = UKFConfig() if cfg is None else cfg
    norm = check_norm(norm)
    w, x = jnp.asarray(w), jnp.asarray(x)
    if w.ndim not in (2, 3) or x.ndim != w.ndim:
        raise ValueError(f"w, x must be [T, .] or [U, T, .]; got {w.shape}, {x.shape}")
    if x.shape[-1] != norm.mean.shape[0]:
        raise ValueError(
            f"x has {x.shape[-1]} sensors but norm has {norm.mean.shape[0]}"
        )
    theta0 = jnp.asarray(theta0, dtype=jnp.result_type(float))
    if theta0.ndim != 1:
        raise ValueError(f"theta0 must be [P], got shape {theta0.shape}")
    check_scale(theta_scale, theta0.shape[0], theta0.dtype)
    return _ukf_filter_jit(
        measure_fn, cfg, unroll, w, x, norm, theta0, theta_scale, mask
    )


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _ukf_filter_jit(measure_fn, cfg, unroll, w, x, norm, theta0, theta_scale, mask):
    ukf = make_ukf(measure_fn, cfg, norm, theta0=theta0, theta_scale=theta_scale)
    if w.ndim == 3:
        return run_fleet(ukf, w, x, mask, unroll=unroll)
    return run_calibrator(ukf, w, x, mask, unroll=unroll)
