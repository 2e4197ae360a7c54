"""A unit's remaining useful life: its trend's posterior, sampled to the first crossing.

For each unit and parameter the trend's posterior given the unit's own trajectory is
closed form (Bayesian linear regression on the fleet's prior, Bishop, *PRML* eq. 3.50-
3.51): ``Lambda = Sigma^-1 + A^T A / s^2``,
``m = Lambda^-1 (Sigma^-1 mu + A^T y / s^2)``, on the AR(1)-whitened rows.
Trends drawn from it, and boundaries drawn from the fleet's spread, are followed from
the unit's age ``now`` over a horizon of twice the longest training life; the first
crossing (linearly interpolated between grid points) is the sample's end of life, the
earliest over the deciding parameters, which names the **driver**. The RUL is the
median of ``end - now`` over the samples, its interval the central ``coverage`` share; a
sample that never crosses within the horizon counts as the horizon (said in
``censored``). With several fault modes (:mod:`jaxcal.prognosis.degradation`) each
sample first draws the unit's mode from its posterior (the modes' weights times the
marginal likelihood of the unit's rows under each, Bishop eq. 3.86), then its trend;
the trend bands are the likeliest mode's. Everything is one jitted program
``vmap``ped over samples and parameters and mapped over units in batches
(``lax.map``), so memory stays bounded on big fleets.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from jaxcal.prognosis.degradation import DegradationModel
from jaxcal.prognosis.trajectories import Trajectories
from jaxcal.prognosis.trends import basis

GRID = 512  # crossing search points over the horizon (interpolated between them)
PLOT_GRID = 160  # points of the trend bands drawn from the first row to the horizon
HORIZON_LIVES = 2.0  # the search runs this many longest training lives past now
UNIT_BATCH = 8  # units per vmapped batch of the unit map


@dataclasses.dataclass(frozen=True)
class RulPrediction:
    """Per unit ``[U]`` (see the module docstring).

    Attributes:
        unit, now: the unit ids and their age at prediction.
        rul, rul_low, rul_high: the median RUL and its ``coverage`` interval.
        driver: the parameter whose boundary most samples cross first.
        driver_share: the share of samples in which it does.
        censored: the share of samples with no crossing within the horizon.
        coverage: the interval's nominal coverage.
        trend_time: ``[U, G]`` ages of the trend bands.
        trend: ``[U, P, 3, G]`` the posterior trend's low / median / high quantiles
            (the trend's own uncertainty, without the noise about it).
        samples: ``[U, K]`` RUL samples (for scoring and plots).
        names: the parameters.
    """

    unit: np.ndarray
    now: np.ndarray
    rul: np.ndarray
    rul_low: np.ndarray
    rul_high: np.ndarray
    driver: tuple[str, ...]
    driver_share: np.ndarray
    censored: np.ndarray
    coverage: float
    trend_time: np.ndarray
    trend: np.ndarray
    samples: np.ndarray
    names: tuple[str, ...]


@functools.partial(jax.jit, static_argnames=("num_samples", "trend", "bands"))
def _predict_all(key, arrays, prior, num_samples: int, trend: str, horizon, bands):
    """The per-unit RUL samples, driver indices and trend bands (mapped over units)."""
    mu, cov, log_w, noise, rho, bound, bound_std, direction, decides, quant = prior
    mixture = mu.shape[0] > 1  # fault modes (degradation module docstring)
    prec = jnp.linalg.inv(cov if mixture else cov[0])  # [M, P, D, D] or [P, D, D]

    def whiten(v, r):
        """Prais-Winsten: the AR(1) residual's rows made independent (valid rows are a
        prefix of the unit's, so a row and the one before it are both used)."""
        head = v[:1] * jnp.sqrt(1.0 - r**2)
        return jnp.concatenate([head, v[1:] - r * v[:-1]])

    def one_unit(args):
        key, s, y, mask, now, start, scale = args  # s, mask [T]; y [T, P]; scalars
        phi = basis(s, trend)  # [T, D]

        def posterior(y_p, mu_p, prec_p, noise_p, rho_p):
            a = whiten(phi, rho_p) * mask[:, None]
            yw = whiten(y_p, rho_p) * mask
            lam = prec_p + a.T @ a / noise_p**2
            rhs = prec_p @ mu_p + a.T @ yw / noise_p**2
            lam_chol = jnp.linalg.cholesky(lam)
            mean = jax.scipy.linalg.cho_solve((lam_chol, True), rhs)
            # the log marginal likelihood of the rows, up to what every mode shares
            # (Bishop, PRML eq. 3.86): m^T Lambda m - mu^T Sigma^-1 mu, log dets
            log_ev = (
                0.5 * (rhs @ mean - mu_p @ prec_p @ mu_p)
                + 0.5 * (jnp.linalg.slogdet(prec_p)[1])
                - jnp.sum(jnp.log(jnp.diag(lam_chol)))
            )
            return mean, lam_chol, log_ev

        per_param = jax.vmap(posterior, in_axes=(1, 0, 0, 0, 0))
        k_beta, k_bound = jax.random.split(key)
        # beta = mean + L^-T z has covariance Lambda^-1 (L the Cholesky factor)
        solve = jax.vmap(lambda l, zz: jax.scipy.linalg.solve_triangular(l.T, zz.T).T)
        if not mixture:
            mean, lam_chol, _ = per_param(y, mu[0], prec, noise * scale, rho)
            z = jax.random.normal(k_beta, (num_samples,) + mean.shape)  # [K, P, D]
            beta = mean + jax.vmap(lambda zz: solve(lam_chol, zz))(z)  # [K, P, D]
        else:
            means, chols, log_ev = jax.vmap(
                per_param, in_axes=(None, 0, 0, None, None)
            )(y, mu, prec, noise * scale, rho)  # [M, P, D], [M, P, D, D], [M, P]
            logits = log_w + log_ev.sum(1)
            mode = jax.random.categorical(
                jax.random.fold_in(key, 1), logits, shape=(num_samples,)
            )
            z = jax.random.normal(k_beta, (num_samples,) + means.shape[1:])
            each = jax.vmap(lambda m, l: m + jax.vmap(lambda zz: solve(l, zz))(z))(
                means, chols
            )  # [M, K, P, D]
            beta = each[mode, jnp.arange(num_samples)]
            best = jnp.argmax(logits)  # the bands show the likeliest mode's trend
            mean, lam_chol = means[best], chols[best]
        b = bound + bound_std * jax.random.normal(k_bound, (num_samples, bound.size))
        grid = now + horizon * jnp.linspace(0.0, 1.0, GRID)  # [G]
        curve = jnp.einsum("gd,kpd->kpg", basis(grid, trend), beta)  # [K, P, G]
        gap = direction[None, :, None] * (curve - b[:, :, None])  # >= 0: crossed
        crossed = gap >= 0
        first = jnp.argmax(crossed, axis=-1)  # [K, P]
        any_cross = crossed.any(axis=-1)
        prev = jnp.maximum(first - 1, 0)
        g0 = jnp.take_along_axis(gap, prev[..., None], -1)[..., 0]
        g1 = jnp.take_along_axis(gap, first[..., None], -1)[..., 0]
        frac = jnp.where(first > 0, -g0 / jnp.where(g1 - g0 > 0, g1 - g0, 1.0), 0.0)
        step = horizon / (GRID - 1)
        end = grid[prev] + jnp.where(first > 0, frac * step, 0.0)
        end = jnp.where(any_cross, end, grid[-1])
        end = jnp.where(decides[None, :], end, jnp.inf)
        rul = jnp.min(end, axis=1) - now  # [K]
        driver = jnp.argmin(end, axis=1)
        censored = ~jnp.any(any_cross & decides[None, :], axis=1)
        if not bands:  # the held-out check needs no trend bands
            return rul, driver, censored
        # the posterior trend at an age is Gaussian (phi . m, phi^T Lambda^-1 phi): its
        # quantiles are exact, no samples needed
        plot = start + (now + horizon - start) * jnp.linspace(0.0, 1.0, PLOT_GRID)
        phi = basis(plot, trend)  # [G, D]
        half = jax.vmap(
            lambda l: jax.scipy.linalg.solve_triangular(l, phi.T, lower=True)
        )
        sd = jnp.sqrt(jnp.sum(half(lam_chol) ** 2, axis=1))  # [P, G]
        centre = mean @ phi.T  # [P, G]
        band = centre[:, None, :] + quant[None, :, None] * sd[:, None, :]  # [P, 3, G]
        return rul, driver, censored, plot, band

    keys = jax.random.split(key, arrays[0].shape[0])
    return jax.lax.map(one_unit, (keys, *arrays), batch_size=UNIT_BATCH)


def predict(
    model: DegradationModel,
    traj: Trajectories,
    key,
    *,
    num_samples: int = 1000,
    coverage: float = 0.9,
    bands: bool = True,
    noise_scale=None,
) -> RulPrediction:
    """The :class:`RulPrediction` of every unit of ``traj`` under ``model``
    (``bands=False``: no trend bands, ``trend_time`` and ``trend`` are empty;
    ``noise_scale [U]``: each unit's noise scale, in place of the model's — the
    held-out check predicts every scale in one call)."""
    if tuple(traj.names) != tuple(model.names):
        raise ValueError(
            f"trajectories of {list(traj.names)}, but the degradation model was "
            f"learned on {list(model.names)}"
        )
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"coverage must be in (0, 1), got {coverage}")
    scale = model.time_scale
    tail = (1.0 - coverage) / 2.0
    prior = (
        model.prior_mean, model.prior_cov, np.log(model.mode_weight),
        model.noise, model.rho,
        model.boundary, model.boundary_std, model.direction, model.decides,
        scipy.stats.norm.ppf([tail, 0.5, 1.0 - tail]),
    )  # fmt: skip
    arrays = (
        traj.time / scale, traj.theta, traj.mask.astype(np.float64),
        traj.now / scale, traj.start / scale,
        np.broadcast_to(
            model.noise_scale
            if noise_scale is None
            else np.asarray(noise_scale, float),
            traj.unit.shape,
        ),
    )  # fmt: skip
    horizon = HORIZON_LIVES * float(model.lives.max()) / scale
    out = jax.device_get(
        _predict_all(key, arrays, prior, num_samples, model.trend, horizon, bands)
    )
    rul, driver, censored = out[:3]
    plot, band = out[3:] if bands else (np.zeros((rul.shape[0], 0)),) * 2
    rul = np.maximum(rul * scale, 0.0)
    low, mid, high = np.quantile(rul, [tail, 0.5, 1.0 - tail], axis=1)
    counts = np.stack([(driver == p).sum(1) for p in range(len(model.names))], 1)
    return RulPrediction(
        unit=traj.unit,
        now=traj.now,
        rul=mid,
        rul_low=low,
        rul_high=high,
        driver=tuple(model.names[i] for i in counts.argmax(1)),
        driver_share=counts.max(1) / num_samples,
        censored=censored.mean(1),
        coverage=coverage,
        trend_time=plot * scale,
        trend=band,
        samples=rul,
        names=model.names,
    )
