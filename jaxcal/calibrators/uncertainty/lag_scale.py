"""The error scale a random-walk filter predicts for its own theta: std and lag bias.

A filter that models theta as a random walk (step std ``q`` per sample) tracks a
drifting parameter with a lag. For a ramp of rate ``r`` per sample and a steady
gain the mean error ``e`` of the update ``e' = (I - K J)(e - r)`` solves
``K J e = -(I - K J) r``; with ``I - K J = P (P + Q)^-1`` (``P`` the posterior
covariance, ``Q = q^2 I``) that is

    e = -P Q^-1 r = -P r / q^2,

a lag of ``P / q^2`` samples: the less the outputs say about a parameter (the larger
its ``P``), the longer the filter trails it. The same ``P`` gives the error's spread.
So the filter predicts its error's size on each sample from quantities it carries:

    scale = h sqrt(diag(P) + (P u / q^2)^2),   u = r / h,

in theta units (``h`` the half box the filter runs in). The drift rate is not known
online; :func:`update_trend` estimates it from the policy's own theta by Brown's
double exponential smoothing (discounted least squares of a line, Brown 1963,
"Smoothing, forecasting and prediction", ch. 7), which needs two vectors of state.

Why the band needs it (``results/policy_any_model``): a policy built on the
filter's step lags a drift by its rate times a lag that depends on the unit's
conditions, so its error is mostly a per-unit bias that a band of one width per time
bucket, pooled over simulated units, covers unevenly. Scaling the band by this
predicted error (:func:`jaxcal.calibrators.uncertainty.conformal.fit_band` with
``scale``) widens it on the units that drift fast or are observed weakly. It does not
make single units alike: the rate estimated online is noisy, and the lag also
depends on the noise's own slow wander.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.typedefs import Array

# Brown's smoothing constant: a line fitted by least squares discounted by 1 - 1/16
# per sample (about the last 32 samples; a few lags of a slow parameter). On the
# simulated band units of the pump (seed 0) and the fan (seed 1) it left less spread
# of coverage between units than 1/32 (leak: std 0.050 against 0.054, 0.087 with no
# scale; experiments outside the repo).
TREND_ALPHA = 1.0 / 16.0


def initial_trend(param_dim: int, dtype) -> Array:
    """``[2, P]`` Brown's two smoothed levels before a stream's first sample (set to
    the first theta by :func:`update_trend`)."""
    return jnp.zeros((2, param_dim), dtype)


def update_trend(
    trend: Array, started: Array, theta: Array, alpha: float = TREND_ALPHA
) -> Array:
    """``[2, P]`` Brown's levels after ``theta`` ``[P]``: ``s1 += a (theta - s1)``,
    ``s2 += a (s1 - s2)``; both start at the first theta (``started`` False)."""
    trend = jnp.where(started, trend, jnp.broadcast_to(theta, trend.shape))
    s1 = trend[0] + alpha * (theta - trend[0])
    s2 = trend[1] + alpha * (s1 - trend[1])
    return jnp.stack([s1, s2]).astype(trend.dtype)


def trend_rate(trend: Array, alpha: float = TREND_ALPHA) -> Array:
    """``[P]`` the drift per sample of Brown's levels: ``a / (1 - a) (s1 - s2)``."""
    return alpha / (1.0 - alpha) * (trend[0] - trend[1])


def filter_error_scale(cov: Array, rate: Array, half: Array, q: float) -> Array:
    """``[P]`` the error the filter predicts for theta (module doc).

    Args:
        cov: ``[P, P]`` the filter's covariance in half-box units (the theta block
            of a joint filter's).
        rate: ``[P]`` theta's drift per sample (theta units; :func:`trend_rate`).
        half: ``[P]`` the half box the filter runs in.
        q: the filter's random-walk std per sample (half-box units).

    Returns:
        ``h sqrt(diag(P) + (P (rate / h) / q^2)^2)`` in theta units.
    """
    bias = cov @ (rate / half) / q**2
    return half * jnp.sqrt(jnp.diagonal(cov) + jnp.square(bias))
