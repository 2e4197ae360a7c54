"""The fleet's degradation model, learned from run-to-failure units.

Each calibrated health parameter of a unit follows a smooth trend in its age,
``theta_p(t) = phi(t / t_ref) . beta_p`` with a basis ``phi`` (:func:`basis`: a
polynomial, or a line plus an exponential, the wear of damage-propagation models),
plus noise. Fitting every run-to-failure unit by weighted least squares gives
the fleet's distribution of trends, a Gaussian prior ``beta_p ~ N(mu_p, Sigma_p)`` over
units — the hierarchical form of the Bayesian degradation model of Gebraeel et al.
(IIE Transactions 37, 2005), with the exponential's rate fixed per family (chosen on
held-out units) so that the trend is linear in its coefficients and the posterior of a
unit stays closed form (:mod:`jaxcal.prognosis.predict`).

The **failure boundary** of a parameter is where the units ended: the mean and spread of
each training unit's fitted trend at its last row (its end of life). A boundary only
decides end of life when the units end near it (its spread over the drift that leads
to it, ``tightness``, at most :attr:`DegradationConfig.max_tightness`); a user may
declare boundaries instead (``boundary={name: limit}``): then those, and only those,
decide.

**Fault modes.** When the fleet failed by more than one mode (C-MAPSS FD003/FD004: a
unit's HPC or its fan degrades), a parameter's drifts split into the units it carries to
their end and the others (:func:`_carriers`), and one Gaussian over all units would
give every unit half of each mode's drift. The prior is then a mixture: one Gaussian
per carrier pattern (the set of parameters a unit carries) that enough units share,
weighted by their share of those units. A unit's posterior weighs each mode by how
well it explains the unit's own trajectory (its marginal likelihood,
:mod:`jaxcal.prognosis.predict`). A fleet of one mode (C-MAPSS FD001/FD002) has one
component, the Gaussian above.

The residual noise is the filtered estimate's: the calibrators' estimates are
autocorrelated, so the std of the residual is widened by ``sqrt((1 + r1) / (1 - r1))``
with ``r1`` its lag-one autocorrelation (the effective sample size of an AR(1) series),
and by ``noise_scale`` (learned on held-out training units by
:func:`jaxcal.prognosis.pipeline.learn_noise_scale` unless given).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.prognosis.trajectories import Trajectories
from jaxcal.prognosis.trends import basis, check_trend, describe, size

MIN_UNITS = 3  # the fleet's spread of trends needs a few run-to-failure units
SHRINK = 0.01  # diagonal loading of the trend prior's covariance (share of diagonal)
# two groups of drifts this many pooled stds apart: a second fault mode (_carriers)
SEPARATION = 4.0
MIN_CARRIERS = 0.1  # the degraded group holds at least this share of the units


@dataclasses.dataclass(frozen=True)
class DegradationConfig:
    trend: str = "poly3"  # a parameter's trend family in age (see basis)
    # a learned boundary decides end of life only if the units' spread at their end is
    # at most this share of the mean drift from start to end
    max_tightness: float = 0.35
    ridge: float = 1e-8  # keeps a short unit's least-squares solve well posed


@dataclasses.dataclass(frozen=True)
class DegradationModel:
    """What the run-to-failure units teach (module docstring); arrays are ``[P, ...]``.

    Attributes:
        names: the parameters.
        time_scale: ages are divided by it (the training units' median life).
        prior_mean, prior_cov: ``[M, P, D]``, ``[M, P, D, D]`` the fleet's trend
            distribution per fault mode (``M = 1`` for a fleet of one mode).
        mode_weight: ``[M]`` each mode's share of the training units.
        modes: ``[M, P]`` the parameters each mode carries to its end.
        noise: ``[P]`` residual std about a trend, autocorrelation-widened.
        noise_scale: the further factor on ``noise`` (held-out calibrated).
        boundary, boundary_std: ``[P]`` where the units end, and its spread.
        direction: ``[P]`` +1 if the parameter rises to its boundary, -1 if it falls.
        tightness: ``[P]`` boundary spread / drift (NaN for a declared boundary).
        decides: ``[P]`` the boundaries that decide end of life.
        declared: ``[P]`` the boundaries the user gave.
        lives: ``[U]`` the training units' lives (last minus first time, plus one).
        rho: ``[P]`` the lag-one autocorrelation of the noise about a trend.
        end_mean, end_std: ``[P]`` where the training units' trends end (the learned
            boundary, kept beside a declared one to compare).
        carriers: ``[U, P]`` the training units whose end each parameter marks
            (:func:`_carriers`).
        trend: the trend family (:func:`basis`).
    """

    names: tuple[str, ...]
    time_scale: float
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    noise: np.ndarray
    noise_scale: float
    boundary: np.ndarray
    boundary_std: np.ndarray
    direction: np.ndarray
    tightness: np.ndarray
    decides: np.ndarray
    declared: np.ndarray
    lives: np.ndarray

    rho: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    end_mean: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    end_std: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    carriers: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    mode_weight: np.ndarray = dataclasses.field(default_factory=lambda: np.ones(1))
    modes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    trend: str = "poly3"

    def to_json(self) -> dict:
        return {
            "parameters": list(self.names),
            "trend": f"{self.trend} in age / {self.time_scale:g}",
            "trend_form": describe(self.trend),
            "noise": dict(zip(self.names, self.noise.tolist(), strict=True)),
            "noise_scale": self.noise_scale,
            "boundary": {
                n: {
                    "value": float(b),
                    "std": float(s),
                    "direction": int(d),
                    "tightness": None if not np.isfinite(t) else float(t),
                    "decides": bool(c),
                    "declared": bool(k),
                    "training_ends": {"mean": float(m), "std": float(e)},
                    "carriers": int(c_count),
                }
                for n, b, s, d, t, c, k, m, e, c_count in zip(
                    self.names,
                    self.boundary,
                    self.boundary_std,
                    self.direction,
                    self.tightness,
                    self.decides,
                    self.declared,
                    self.end_mean,
                    self.end_std,
                    self.carriers.sum(0),
                    strict=True,
                )
            },
            "modes": [
                {
                    "carries": [n for n, c in zip(self.names, m, strict=True) if c],
                    "weight": float(w),
                }
                for m, w in zip(self.modes, self.mode_weight, strict=True)
            ],
            "training_units": int(self.lives.size),
            "training_life": {
                "mean": float(self.lives.mean()),
                "min": float(self.lives.min()),
                "max": float(self.lives.max()),
            },
        }


@functools.partial(jax.jit, static_argnames="trend")
def _fit_all(s, y, mask, trend: str, ridge: float):
    """``beta [U, P, D]``, residuals ``[U, T, P]`` of every unit's trend (vmapped)."""

    def one(s_u, y_u, m_u):  # s_u, m_u [T]; y_u [T]
        a = basis(s_u, trend) * m_u[:, None]
        gram = a.T @ a + ridge * jnp.eye(size(trend))
        beta = jnp.linalg.solve(gram, a.T @ (y_u * m_u))
        return beta, (y_u - basis(s_u, trend) @ beta) * m_u

    per_param = jax.vmap(one, in_axes=(None, 1, None), out_axes=(0, 1))
    return jax.vmap(per_param)(s, y, mask)


def _carriers(drift: np.ndarray) -> np.ndarray:
    """``[U]`` the units whose end of life a parameter marks, from its drift over each
    unit's record: every unit, unless the drifts split into two groups
    :data:`SEPARATION` pooled stds apart (Otsu's split of the sorted drifts), the larger
    one degraded and the other not — units that failed by another fault mode (C-MAPSS
    FD003/FD004: HPC or fan). Then the degraded group, if it holds at least
    :data:`MIN_CARRIERS` of the units."""
    every = np.ones(drift.size, bool)
    y = drift * (np.sign(drift.sum()) or 1.0)  # degradation along the fleet's way
    order = np.sort(y)
    n = y.size
    k = np.arange(2, n - 1)  # left group order[:k], right order[k:], 2+ units each
    if k.size == 0:
        return every
    c1, c2 = np.cumsum(order), np.cumsum(order**2)
    left_mean, right_mean = c1[k - 1] / k, (c1[-1] - c1[k - 1]) / (n - k)
    within = (c2[k - 1] - k * left_mean**2) + (
        (c2[-1] - c2[k - 1]) - (n - k) * right_mean**2
    )
    between = k * (n - k) * (right_mean - left_mean) ** 2  # Otsu: n^2 x between var
    best = int(np.argmax(between))
    pooled = np.sqrt(max(within[best], 0.0) / (n - 2))
    gap = right_mean[best] - left_mean[best]
    enough = n - k[best] >= max(MIN_UNITS, MIN_CARRIERS * n)
    if gap > SEPARATION * pooled and left_mean[best] < gap / SEPARATION and enough:
        return y >= order[k[best]]
    return every


def _modes(carriers: np.ndarray, need: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """The fault modes: ``([M, P] carrier patterns, [M] unit masks)``, one per pattern
    of :func:`_carriers` that at least ``need`` units share (a mode's prior needs more
    units than trend coefficients); a single mode of every unit when fewer than two
    patterns have so many."""
    patterns, inverse = np.unique(carriers, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse, minlength=len(patterns))
    kept = np.flatnonzero(counts >= need)
    if kept.size < 2:
        return np.ones((1, carriers.shape[1]), bool), [np.ones(len(carriers), bool)]
    return patterns[kept], [inverse == k for k in kept]


def _prior(beta: np.ndarray, trend: str) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian over units of trend coefficients ``beta [U, P, D]``:
    ``([P, D] mean, [P, D, D] covariance)``, its diagonal loaded by :data:`SHRINK`."""
    cov = np.stack([np.cov(beta[:, p].T) for p in range(beta.shape[1])])
    # a little diagonal loading: a spread over few units is noisy, and must invert
    return beta.mean(0), cov * (1.0 + SHRINK * np.eye(size(trend)))


def require_units(num_units: int, trend: str, label: str = "train") -> None:
    """Raise ``ValueError`` unless ``num_units`` run-to-failure units can give a prior
    of ``trend``: its covariance over units needs more units than coefficients."""
    need = max(MIN_UNITS, size(trend) + 1)
    if num_units < need:
        raise ValueError(
            f"{label}: {num_units} run-to-failure unit(s); the fleet's degradation "
            f"needs at least {need} for a {trend} trend (a simpler trend= needs fewer)"
        )


def fit(
    train: Trajectories,
    config: DegradationConfig = DegradationConfig(),
    boundary: Mapping[str, float] | None = None,
    noise_scale: float = 1.0,
) -> DegradationModel:
    """The :class:`DegradationModel` of run-to-failure trajectories ``train``.

    Each unit's last used row is its end of life. ``boundary``: parameter -> declared
    limit (its end of life, whatever the units did). Raises ``ValueError`` for fewer
    than :data:`MIN_UNITS` units, a declared boundary naming no parameter, or no
    boundary that decides (naming each one's tightness).
    """
    boundary = dict(boundary or {})
    unknown = sorted(set(boundary) - set(train.names))
    if unknown:
        raise ValueError(
            f"boundary names {unknown}: not calibrated parameters {list(train.names)}"
        )
    num_units = train.unit.size
    check_trend(config.trend)
    require_units(num_units, config.trend)
    lives = train.now - train.start + 1.0
    time_scale = float(np.median(lives))
    s = train.time / time_scale
    mask = train.mask.astype(np.float64)
    beta, res = _fit_all(s, train.theta, mask, config.trend, config.ridge)
    beta, res = np.asarray(beta), np.asarray(res)
    dof = mask.sum() - num_units * size(config.trend)
    sigma = np.sqrt((res**2).sum(axis=(0, 1)) / max(dof, 1.0))
    lag = (res[:, 1:] * res[:, :-1]).sum(axis=(0, 1)) / np.maximum(
        (res**2).sum(axis=(0, 1)), 1e-300
    )
    rho = np.clip(lag, 0.0, 0.95)
    noise = np.maximum(sigma * np.sqrt(1 - rho**2), 1e-12)  # the AR(1) innovation

    phi_end = np.asarray(basis(train.now / time_scale, config.trend))  # [U, D]
    phi_start = np.asarray(basis(train.start / time_scale, config.trend))
    end = np.einsum("ud,upd->up", phi_end, beta)
    start = np.einsum("ud,upd->up", phi_start, beta)
    # per parameter, the units whose end it marks (all, but for a second fault mode)
    carriers = np.stack(
        [_carriers(end[:, p] - start[:, p]) for p in range(end.shape[1])], 1
    )
    count = carriers.sum(0)
    drift = (carriers * (end - start)).sum(0) / count
    learned = (carriers * end).sum(0) / count
    spread = np.sqrt(
        (carriers * (end - learned) ** 2).sum(0) / np.maximum(count - 1, 1)
    )
    tightness = spread / np.maximum(np.abs(drift), 1e-300)
    declared = np.array([n in boundary for n in train.names])
    value = np.array(
        [boundary.get(n, b) for n, b in zip(train.names, learned, strict=True)]
    )
    direction = np.sign(np.where(declared, value - start.mean(0), drift))
    direction = np.where(direction == 0, 1.0, direction)
    # a declared limit is the user saying what ends a life: then only declared ones do
    decides = declared if declared.any() else tightness <= config.max_tightness
    if not decides.any():
        detail = ", ".join(
            f"{n} {t:.2f}" for n, t in zip(train.names, tightness, strict=True)
        )
        raise ValueError(
            "no parameter's end of life is consistent across the training units "
            f"(tightness, the spread at the end over the drift to it: {detail}; at "
            f"most {config.max_tightness} decides): declare a limit with "
            "boundary=name:value"
        )
    modes, members = _modes(carriers, max(MIN_UNITS, size(config.trend) + 1))
    priors = [_prior(beta[m], config.trend) for m in members]
    counts = np.array([m.sum() for m in members], float)
    return DegradationModel(
        names=train.names,
        time_scale=time_scale,
        prior_mean=np.stack([p[0] for p in priors]),
        prior_cov=np.stack([p[1] for p in priors]),
        mode_weight=counts / counts.sum(),
        modes=modes,
        noise=noise,
        rho=rho,
        end_mean=learned,
        end_std=spread,
        carriers=carriers,
        noise_scale=float(noise_scale),
        boundary=value,
        boundary_std=np.where(declared, 0.0, spread),
        direction=direction,
        tightness=np.where(declared, np.nan, tightness),
        decides=decides,
        declared=declared,
        lives=lives,
        trend=config.trend,
    )
