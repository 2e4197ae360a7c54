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

Float64 is recommended (covariance updates lose positive definiteness in float32 at
``q = r = 0.01``); the Cholesky factorisation adds ``jitter`` to the diagonal.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from flax import struct
from jax.scipy.linalg import cho_factor, cho_solve

from jaxcal.calibrators.interface import (
    Calibrator,
    CalOutput,
    CalStepOutput,
    MeasureFn,
    SensorNorm,
    check_norm,
    check_scale,
    run_calibrator,
    run_fleet,
)
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
    """Gaussian belief over the scaled parameters ``z = theta / theta_scale``."""

    mean: Array  # [P]
    cov: Array  # [P, P]


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
        ``innovation [S]`` (normalised ``x_n - E[x_n]`` before the update),
        ``log_likelihood []`` (of the normalised ``x_t`` given the past) and, if asked,
        ``theta_cov [P, P]``.
    """
    norm = check_norm(norm)
    theta0 = jnp.asarray(theta0, dtype=jnp.result_type(float))
    if theta0.ndim != 1:
        raise ValueError(f"theta0 must be [P], got shape {theta0.shape}")
    num_params = theta0.shape[0]
    scale = check_scale(theta_scale, num_params, theta0.dtype)
    wm, wc, spread = unscented_weights(num_params, cfg)
    eye = jnp.eye(num_params, dtype=theta0.dtype)

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> UKFState:
        del key, w0, x0  # the prior is fixed by the factory
        return UKFState(mean=theta0 / scale, cov=cfg.prior_std**2 * eye)

    def step(state: UKFState, w_t: Array, x_t: Array) -> tuple[UKFState, CalStepOutput]:
        def measure_n(z: Array) -> Array:
            return (measure_fn(w_t, scale * z) - norm.mean) / norm.std

        # Prediction (Särkkä alg. 5.14, identity dynamics => exact): m, P + Q.
        mean_prior = state.mean
        cov_prior = state.cov + cfg.q**2 * eye
        # Update: propagate the sigma points through the normalised measurement model.
        points = sigma_points(mean_prior, cov_prior, spread, cfg.jitter)  # [K, P]
        y_points = jax.vmap(measure_n)(points)  # [K, S]
        y_mean = wm @ y_points
        dy = y_points - y_mean
        dz = points - mean_prior
        s_cov = dy.T @ (wc[:, None] * dy) + cfg.r**2 * jnp.eye(
            dy.shape[1], dtype=dy.dtype
        )
        cross = dz.T @ (wc[:, None] * dy)  # [P, S]
        s_chol = cho_factor(s_cov, lower=True)
        gain = cho_solve(s_chol, cross.T).T  # C S^-1
        innovation = (x_t - norm.mean) / norm.std - y_mean
        mean = mean_prior + gain @ innovation
        cov = cov_prior - gain @ s_cov @ gain.T
        cov = 0.5 * (cov + cov.T)  # keep symmetric against round-off
        log_likelihood = -0.5 * (
            innovation @ cho_solve(s_chol, innovation)
            + 2.0 * jnp.sum(jnp.log(jnp.diag(s_chol[0])))
            + innovation.shape[0] * math.log(2.0 * math.pi)
        )
        if cfg.posterior_xhat:
            xhat = measure_fn(w_t, scale * mean)
        else:  # the predicted measurement mean, free but one step behind the update
            xhat = norm.mean + norm.std * y_mean
        aux = {
            "theta_std": scale * jnp.sqrt(jnp.clip(jnp.diag(cov), 0.0)),
            "innovation": innovation,
            "log_likelihood": log_likelihood,
        }
        if cfg.return_cov:
            aux["theta_cov"] = cov * scale[:, None] * scale[None, :]
        new_state = UKFState(mean=mean, cov=cov)
        return new_state, CalStepOutput(theta=scale * mean, xhat=xhat, aux=aux)

    return Calibrator(init=init, step=step)


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
