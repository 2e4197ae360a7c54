"""Exact Kalman filter for linear-Gaussian models (the reference for the UKF).

Model (Särkkä 2013, "Bayesian Filtering and Smoothing", theorem 4.2)::

    theta_t = A theta_{t-1} + xi_t,    xi ~ N(0, Q)
    y_t     = H_t theta_t + b_t + eps_t, eps ~ N(0, R)

A UKF is exact on such a model (the unscented transform of an affine map reproduces the
mean and covariance), so :func:`kalman_filter` is the answer the UKF in
:mod:`jaxcal.calibrators.ukf` must reproduce to round-off. Prediction comes before the
update at every step, as in the UKF, so ``(mean0, cov0)`` is the belief *before*
``theta_0``'s random-walk step.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import cho_factor, cho_solve

from jaxcal.typedefs import Array


class KalmanOutput(NamedTuple):
    """Filtered moments per step."""

    mean: Array  # [T, P] E[theta_t | y_0..t]
    cov: Array  # [T, P, P] Cov[theta_t | y_0..t]
    y_pred: Array  # [T, S] E[y_t | y_0..t-1]
    log_likelihood: Array  # [T] log p(y_t | y_0..t-1)


@jax.jit
def kalman_filter(
    y: Array,
    obs_matrix: Array,
    obs_offset: Array,
    q_cov: Array,
    r_cov: Array,
    mean0: Array,
    cov0: Array,
    transition: Array | None = None,
) -> KalmanOutput:
    """Filter a linear-Gaussian state-space model with ``lax.scan``.

    Args:
        y: observations ``[T, S]``.
        obs_matrix: ``H``, ``[S, P]`` or time-varying ``[T, S, P]``.
        obs_offset: ``b``, ``[S]`` or ``[T, S]``.
        q_cov: process noise ``Q`` ``[P, P]``.
        r_cov: observation noise ``R`` ``[S, S]``.
        mean0: prior mean ``[P]``.
        cov0: prior covariance ``[P, P]``.
        transition: ``A`` ``[P, P]``; ``None`` is the identity (random walk).

    Returns:
        :class:`KalmanOutput` with ``[T, ...]`` entries.
    """
    num_steps, num_obs = y.shape
    num_params = mean0.shape[0]
    h_seq = jnp.broadcast_to(obs_matrix, (num_steps, num_obs, num_params))
    b_seq = jnp.broadcast_to(obs_offset, (num_steps, num_obs))
    a_mat = jnp.eye(num_params, dtype=mean0.dtype) if transition is None else transition

    def body(carry, inputs):
        mean, cov = carry
        y_t, h_t, b_t = inputs
        mean = a_mat @ mean
        cov = a_mat @ cov @ a_mat.T + q_cov
        y_pred = h_t @ mean + b_t
        s_cov = h_t @ cov @ h_t.T + r_cov
        s_chol = cho_factor(s_cov, lower=True)
        gain = cho_solve(s_chol, h_t @ cov).T  # P H^T S^-1 (cov symmetric)
        innovation = y_t - y_pred
        mean = mean + gain @ innovation
        cov = cov - gain @ s_cov @ gain.T
        cov = 0.5 * (cov + cov.T)
        log_likelihood = -0.5 * (
            innovation @ cho_solve(s_chol, innovation)
            + 2.0 * jnp.sum(jnp.log(jnp.diag(s_chol[0])))
            + num_obs * math.log(2.0 * math.pi)
        )
        return (mean, cov), KalmanOutput(mean, cov, y_pred, log_likelihood)

    _, out = lax.scan(body, (mean0, cov0), (y, h_seq, b_seq))
    return out
