"""The numerics of one UKF step: settings, belief, the scaled unscented transform and
the measurement update (Särkkä 2013, "Bayesian Filtering and Smoothing", alg. 5.14).

:mod:`jaxcal.calibrators.ukf` assembles these into the filter; the state-space model,
the augmented state of a model with memory and the treatment of missing outputs are
described there. Everything here is a pure array function of a static
:class:`UKFConfig`: :func:`unscented_weights` and :func:`sigma_points` (the
transform), :func:`process_noise` and :func:`joint_prior` (the factory's constants),
:func:`predict`, :func:`update` and :func:`step_aux` (one step).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct
from jax.scipy.linalg import cho_factor, cho_solve

from jaxcal.calibrators.interface import Measurement
from jaxcal.typedefs import Array


@dataclasses.dataclass(frozen=True)
class UKFConfig:
    """Static UKF settings (hashable, closed over by
    :func:`~jaxcal.calibrators.ukf.make_ukf`)."""

    q: float = 0.01  # random-walk std per step, scaled-theta units (paper: 0.01)
    r: float = 0.01  # noise std in units of Measurement.noise_std (paper: 0.01)
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


class _Prediction(NamedTuple):
    """One unscented transform of ``(z_{t-1}, theta_t)`` through the model's step."""

    mean: Array  # [n] predicted a = [z / state_scale, theta / theta_scale]
    cov: Array  # [n, n] its covariance (the parameter block exact)
    da: Array  # [K, n] the sigma points' deviations from ``mean``
    y_mean: Array  # [S] predicted normalised measurement
    dy: Array  # [K, S] the sigma points' deviations from ``y_mean``


def process_noise(
    cfg: UKFConfig, eye: Array, s_q: Array, s_scale: Array
) -> tuple[Array, Array]:
    """``(q_theta, q_state)``, both ``[n, n]``: ``q`` on the parameters before the
    transform (``theta_t = theta_{t-1} + xi_t`` enters ``x_t``), ``state_q`` on ``z_t``
    after it (it enters ``x_{t+1}``)."""
    num_states, num_params = s_scale.shape[0], eye.shape[0]
    n = num_states + num_params
    q_theta = (
        jnp.zeros((n, n), eye.dtype).at[num_states:, num_states:].set(cfg.q**2 * eye)
    )
    q_state = jnp.diag(
        jnp.concatenate([(s_q / s_scale) ** 2, jnp.zeros((num_params,), eye.dtype)])
    )
    return q_theta, q_state


def joint_prior(
    at_rest, u0: Array, cov_u: Array, cfg: UKFConfig, s_std: Array, s_scale: Array
) -> UKFState:
    """The prior of ``[z0 / state_scale, u0]`` for a model with memory.

    The initial state depends on the unknown parameters (a cell at rest: ``z0 =
    at_rest(u) = init(w0, theta)``), so its prior is the unscented transform of
    ``at_rest`` over the parameter prior ``N(u0, cov_u)``, cross-covariance included,
    plus ``state_std``.
    """
    wm_p, wc_p, spread_p = unscented_weights(u0.shape[0], cfg)
    points = sigma_points(u0, cov_u, spread_p, cfg.jitter)  # [2P + 1, P]
    z_points = jax.vmap(lambda u: jnp.asarray(at_rest(u), u0.dtype))(points) / s_scale
    z_mean = wm_p @ z_points
    dz, du = z_points - z_mean, points - u0
    cov_zz = dz.T @ (wc_p[:, None] * dz) + jnp.diag((s_std / s_scale) ** 2)
    cov_zu = dz.T @ (wc_p[:, None] * du)
    cov = jnp.block([[cov_zz, cov_zu], [cov_zu.T, cov_u]])
    return UKFState(mean=jnp.concatenate([z_mean, u0]), cov=cov)


def predict(
    state: UKFState, propagate, noise, weights, cfg: UKFConfig, num_states: int
) -> _Prediction:
    """The prediction: the sigma points of ``(z_{t-1}, theta_t)`` (``noise =
    (q_theta, q_state)``, ``weights = (wm, wc, spread)``) through ``propagate(a) ->
    (z_t / state_scale, normalised x_t)``. The parameter block is carried unchanged:
    its prediction stays exact."""
    q_theta, q_state = noise
    wm, wc, spread = weights
    mean_prior = state.mean
    cov_prior = state.cov + q_theta
    points = sigma_points(mean_prior, cov_prior, spread, cfg.jitter)  # [K, n]
    z_points, y_points = jax.vmap(propagate)(points)  # [K, Z], [K, S]
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
    return _Prediction(mean_pred, cov_pred, da, y_mean, dy)


def update(pred: _Prediction, x_t: Array, measurement: Measurement, weights, r: float):
    """The measurement update on the observed outputs of ``x_t``
    (:func:`_observed_only`): ``(mean, cov, s_cov, innovation, log_likelihood)``,
    the innovation and its covariance ``S`` in the compared units
    ``(x - centre) / noise_std`` of ``measurement``, where ``R = r^2 I``."""
    centre, noise_std = measurement
    wc, dy = weights[1], pred.dy
    eye_s = jnp.eye(dy.shape[1], dtype=dy.dtype)
    s_cov = dy.T @ (wc[:, None] * dy) + r**2 * eye_s
    cross = pred.da.T @ (wc[:, None] * dy)  # [n, S]
    s_cov, cross, innovation = _observed_only(
        x_t, s_cov, cross, (x_t - centre) / noise_std - pred.y_mean, eye_s
    )
    s_chol = cho_factor(s_cov, lower=True)
    gain = cho_solve(s_chol, cross.T).T  # C S^-1
    mean = pred.mean + gain @ innovation
    cov = pred.cov - gain @ s_cov @ gain.T
    cov = 0.5 * (cov + cov.T)  # keep symmetric against round-off
    log_likelihood = -0.5 * (
        innovation @ cho_solve(s_chol, innovation)
        + 2.0 * jnp.sum(jnp.log(jnp.diag(s_chol[0])))
        + innovation.shape[0] * math.log(2.0 * math.pi)
        - jnp.sum(jnp.isnan(x_t)) * math.log(2.0 * math.pi)  # observed only
    )
    return mean, cov, s_cov, innovation, log_likelihood


def step_aux(
    cfg: UKFConfig, cov, s_cov, innovation, log_likelihood, z_post, scale, s_scale
) -> dict:
    """The step's ``aux``: the posterior stds, the innovation and its predicted std,
    the likelihood; the filtered state with hidden states; ``theta_cov`` if asked."""
    num_states = s_scale.shape[0]
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
    return aux


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
