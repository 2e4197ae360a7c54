"""The streaming std of least squares (:func:`drift_std`), honest when theta drifts.

The Laplace std ``(J^T J)^-1`` assumes theta constant over the window; a drifting
theta is seen late, by the window's lag (half a window), and the 90 % interval of
the Laplace std held the truth on 0-15 % of the rows of a drifting parameter
(``experiments/std_coverage.py``, ``results/std_coverage``). So the reported std is the
Gaussian-equivalent std (half-width / 1.6449, the convention of
:mod:`jaxcal.calibrators.uncertainty.conformal`) of a 90 % interval of ``N(b, s_L^2 +
v_b)``, times an online scale:

* ``b = -L s``, the lag bias to first order: ``s`` theta's drift per sample, ``L =
  -(J^T J)^-1 J^T D`` the lag matrix, ``D`` the residual's response to a drift
  within the window (``-age_i J_i`` for a static model; through the simulation for
  one with memory). ``s`` is read off the estimate's own past (it moves with the
  truth, lag for lag) between two estimates ``HISTORY`` windows apart at most;
  ``v_b`` is the variance that leaves in ``b``, and ``|b|`` is debiased
  (``b^2 - v_b``, floored at 0) so that a constant theta is not widened by the noise
  of its own slope.
* The scale is adaptive conformal inference (Gibbs & Candès 2021): an estimate
  stands for theta at its centre, ``t - lag``, so the estimate issued then is checked
  against the current one (its error, up to noise of about the same size); each
  check that falls outside its interval widens the scale, each inside narrows it,
  for a long-run miss rate near 10 %. It catches what the linear lag model misses: a
  drift rate that changes (the heat exchanger's accelerating fouling), a wrong
  noise level.

``aux["laplace_std"]`` keeps the fit's own std.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from flax import struct
from jax.scipy.special import ndtr, ndtri

from jaxcal.typedefs import Array

LEVEL = 0.9  # the interval the reported std is the Gaussian-equivalent of
Z_LEVEL = 1.6448536269514722  # its two-sided normal quantile: half-width / std
HISTORY = 3  # past estimates kept to measure the drift, in windows
# The online check (adaptive conformal inference): the log-scale step per check and
# the checks' target miss rate. Set on simulated window means (constant, linear,
# accelerating, saturating, random-walk and step drifts; 240 samples, window 32),
# where 0.08 gave 0.88-0.91 coverage and 0.10 gave 0.85-0.90, and on the tank and
# the thermal model of experiments/std_coverage.py, whose checks miss a little more
# often than their estimates do; not on the heat exchanger's test units.
ADAPT_STEP, PROXY_MISS = 0.1, 0.09
LOG_SCALE_MAX = 8.0  # the scale stays within exp(+-8)


@struct.dataclass
class DriftHistory:
    """The estimate's recent past (scaled units), to measure how fast theta drifts."""

    t: Array  # [] samples used so far
    z: Array  # [H, P] past estimates, H = HISTORY * window (a ring: slot t % H)
    var: Array  # [H, P] their Laplace variances
    centre: Array  # [H, P] the time each estimate stands for: t - its lag
    std: Array  # [H, P] the std reported with each
    filled: Array  # [H] bool, False until a slot holds an estimate (the state stays
    # finite: the guard takes a non-finite state for a failed update)
    log_scale: Array  # [P] the online check's scale of the std (log)


def init_drift_history(z0: Array, window: int) -> DriftHistory:
    """An empty :class:`DriftHistory` for ``HISTORY * window`` estimates of ``[P]``."""
    shape = (HISTORY * window, z0.shape[0])
    return DriftHistory(
        t=jnp.zeros((), z0.dtype),
        z=jnp.broadcast_to(z0, shape),
        var=jnp.zeros(shape, z0.dtype),
        centre=jnp.full(shape, -1.0, z0.dtype),
        std=jnp.zeros(shape, z0.dtype),
        filled=jnp.zeros(shape[:1], bool),
        log_scale=jnp.zeros(shape[1:], z0.dtype),
    )


def prior_age(history: DriftHistory) -> Array:
    """``[P]`` age (samples) of the previous estimate, the prior's pseudo-data."""
    last = (history.t.astype(jnp.int32) - 1) % history.z.shape[0]
    return history.t - history.centre[last]


def interval_half_width(mu: Array, sigma: Array, level: float = LEVEL) -> Array:
    """``h`` with ``P(|mu + sigma e| <= h) = level``, ``e ~ N(0, 1)`` (elementwise).

    The root lies in ``[mu + z1 sigma, mu + z2 sigma]`` (``z1``, ``z2`` the one- and
    two-sided quantiles); the coverage is increasing and concave in ``h`` there, so
    Newton's method from the lower end rises monotonically to it (4 steps: the
    bracket is narrow).
    """
    sigma = jnp.maximum(sigma, jnp.finfo(sigma.dtype).tiny)
    low = mu + ndtri(level) * sigma
    high = mu + ndtri(0.5 + 0.5 * level) * sigma
    h = low
    for _ in range(4):
        upper, lower = (h - mu) / sigma, (-h - mu) / sigma
        gap = ndtr(upper) - ndtr(lower) - level
        slope = (jnp.exp(-0.5 * upper**2) + jnp.exp(-0.5 * lower**2)) / (
            jnp.sqrt(2.0 * jnp.pi) * sigma
        )
        h = jnp.clip(h - gap / slope, low, high)
    return h


class _DriftRate(NamedTuple):
    slope: Array  # [P] theta's drift per sample (scaled units), 0 where unknown
    var: Array  # [P] its variance, 0 where unknown
    span: Array  # [P] samples between the two estimates, 1 where unknown
    known: Array  # [P] bool


def _drift_rate(history: DriftHistory, z_a, var_a, centre_a, older) -> _DriftRate:
    """Theta's drift per sample between the estimate ``z_a [P]`` (variance
    ``var_a``, standing for time ``centre_a``) and the kept estimate among ``older
    [H]`` with the smallest slope variance (none: not known)."""
    cols = jnp.arange(z_a.shape[0])
    span = centre_a[None] - history.centre  # [H, P]
    known = older[:, None] & (span >= 1.0)
    span = jnp.where(known, span, 1.0)
    slope_var = jnp.where(known, (var_a[None] + history.var) / span**2, jnp.inf)
    ref = jnp.argmin(slope_var, axis=0)  # [P]
    known, span = known[ref, cols], span[ref, cols]
    slope = jnp.where(known, (z_a - history.z[ref, cols]) / span, 0.0)
    return _DriftRate(slope, jnp.where(known, slope_var[ref, cols], 0.0), span, known)


def _checked_scale(
    history: DriftHistory, z, var, lag_diag, offset, offset_var, info_rows, ages
) -> Array:
    """``[P]`` the online check's new log-scale (module docstring).

    The estimate ``z`` stands for theta at its centre, the time ``tau = t - lag``
    of an earlier estimate, whose own-lag error is then about ``z_tau - z``; the
    ``offset`` that other parameters' drift causes (the same in both) is added as
    predicted. The check's noise, against ``z_tau``'s alone, is ``z``'s variance
    less twice their covariance (``rho var_tau`` for one parameter, ``rho`` the share
    of ``z``'s information, ``info_rows [M, P]`` per residual row, in the samples
    both windows hold: ``ages [M]`` at least the delay), plus the offset's. A check
    outside the interval issued at ``tau`` (widened by that excess) raises the
    scale, one inside lowers it: adaptive conformal inference (Gibbs & Candès 2021)
    for a miss rate of ``PROXY_MISS``.
    """
    size, cols = history.z.shape[0], jnp.arange(z.shape[0])
    now = history.t.astype(jnp.int32)
    delay = jnp.round(lag_diag).astype(jnp.int32)
    slot = (now - delay) % size
    checked = (delay > 0) & (delay < size) & history.filled[slot]
    proxy = history.z[slot, cols] - z + offset
    both = jnp.sum((ages[:, None] >= delay[None]) * info_rows, axis=0)
    rho = both / jnp.maximum(jnp.sum(info_rows, axis=0), jnp.finfo(z.dtype).tiny)
    excess = var - 2.0 * rho * history.var[slot, cols] + offset_var
    reach = Z_LEVEL**2 * jnp.maximum(history.std[slot, cols] ** 2 + excess, 0.0)
    step = ADAPT_STEP * ((proxy**2 > reach).astype(z.dtype) - PROXY_MISS)
    return jnp.clip(
        history.log_scale + jnp.where(checked, step, 0.0), -LOG_SCALE_MAX, LOG_SCALE_MAX
    )


def drift_std(
    history: DriftHistory,
    z: Array,
    cov: Array,
    jac: Array,
    drift_jac: Array,
    ages: Array,
    window: int,
) -> tuple[Array, Array, DriftHistory]:
    """The honest std of a window estimate under drift (module docstring).

    Args:
        history: the past estimates.
        z: ``[P]`` the window's estimate (scaled units).
        cov: ``[Q, Q]`` ``(J^T J)^-1``, ``Q >= P`` unknowns, theta's first.
        jac: ``[M, Q]`` the residual's Jacobian at ``z``.
        drift_jac: ``[M, P]`` the residual's change with a drift ``s`` of theta
            over the window (``z_k = z - age_k s``, the newest sample's age 0): for
            a static model ``-age_i J_i``; for one with memory the simulation's.
        ages: ``[M]`` each residual row's sample age (-1: a row of no sample, a
            prior).
        window: ``N``, the samples in the window.

    Returns:
        ``(std [P], laplace_std [P], history)`` in scaled units, the history with
        this estimate added.
    """
    num_params, size = z.shape[0], history.z.shape[0]
    now = history.t.astype(jnp.int32)
    var = jnp.diagonal(cov)[:num_params]
    lag = -(cov @ (jac.T @ drift_jac))[:num_params]
    lag_diag = jnp.diagonal(lag)
    centre = history.t - lag_diag
    # 1. the lag bias, from the drift per sample between a newer estimate (the
    # current one, or the one of a window ago: its window and the current one share
    # no sample) and the older kept one that measures it best; per parameter, the
    # pair that leaves the smaller variance
    stamp = now - 1 - (now - 1 - jnp.arange(size)) % size  # [H] each slot's time
    current = _drift_rate(history, z, var, centre, history.filled & (stamp < now))
    newer = (now - window) % size
    past = _drift_rate(
        history, history.z[newer], history.var[newer], history.centre[newer],
        history.filled & (stamp < now - window),
    )  # fmt: skip
    # a slope through the current estimate shares its noise: err - bias moves by
    # (1 + lag / span) times it
    shared = jnp.where(current.known, 2.0 * lag_diag / current.span * var, 0.0)
    shared = jnp.maximum(shared, 0.0)
    use_past = past.known & (
        lag_diag**2 * past.var <= lag_diag**2 * current.var + shared
    )
    slope = jnp.where(use_past, past.slope, current.slope)
    slope_var = jnp.where(use_past, past.var, current.var)
    shared = jnp.where(use_past, 0.0, shared)
    bias = -lag @ slope  # the estimate's error, theta_hat - theta, to first order
    own = -lag_diag * slope  # the part of it that is its own lag
    bias_var = lag**2 @ slope_var
    sigma = jnp.sqrt(var + bias_var + shared)
    mu = jnp.sqrt(jnp.maximum(bias**2 - bias_var, 0.0))
    base = interval_half_width(mu, sigma) / Z_LEVEL
    # 2. the online check, once the window is full (a steady lag)
    log_scale = _checked_scale(
        history, z, var, lag_diag, bias - own, bias_var - lag_diag**2 * slope_var,
        jac[:, :num_params] ** 2, ages,
    )  # fmt: skip
    log_scale = jnp.where(now >= window, log_scale, history.log_scale)
    std = base * jnp.exp(log_scale)
    here = now % size
    new_history = DriftHistory(
        t=history.t + 1.0,
        z=history.z.at[here].set(z),
        var=history.var.at[here].set(var),
        centre=history.centre.at[here].set(centre),
        std=history.std.at[here].set(std),
        filled=history.filled.at[here].set(True),
        log_scale=log_scale,
    )
    return std, jnp.sqrt(var), new_history
