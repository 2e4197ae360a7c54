"""Theta paths of simulated units: drawn across the box, or the data's own drifts.

:mod:`jaxcal.training.data.simulated` makes labelled units along real units' conditions;
this module says how their theta moves.

* :func:`theta_paths` draws degradation-like paths, per unit and parameter
  (monotone, smooth, the whole box reachable within a unit's life):
  ``theta(t) = a + (b - a) s^k`` with ``s = t / (L - 1)``, ``a, b`` uniform in the box
  and ``k`` uniform in [1, 2]; a share ``constant_share`` of the units keeps
  ``b = a`` (a constant parameter, the case a band must not be too wide for).
* :func:`estimated_drifts` reads the drifts of the data themselves: the front door's
  UKF over the real units, its theta fitted per unit by a quadratic in the unit's own
  time; :func:`drift_paths` lays them along other units (``simulate.paths=data``).
"""

from __future__ import annotations

import jax
import numpy as np
import pandas as pd

from jaxcal.calibrators.front.door import calibrate
from jaxcal.data.padded import Padded
from jaxcal.problem import Problem


def theta_paths(
    key: jax.Array,
    low: np.ndarray,
    high: np.ndarray,
    lengths: np.ndarray,
    num_steps: int,
    constant_share: float = 0.25,
) -> np.ndarray:
    """``[U, T, P]`` theta trajectories in ``[low, high]`` (module doc); rows past a
    unit's length hold its last value."""
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    num_units, num_params = len(lengths), len(low)
    k_a, k_b, k_k, k_c = jax.random.split(key, 4)
    uniform = lambda k, shape: np.asarray(jax.random.uniform(k, shape))  # noqa: E731
    start = low + (high - low) * uniform(k_a, (num_units, num_params))
    end = low + (high - low) * uniform(k_b, (num_units, num_params))
    power = 1.0 + uniform(k_k, (num_units, num_params))
    constant = uniform(k_c, (num_units,)) < constant_share
    end = np.where(constant[:, None], start, end)
    span = np.maximum(np.asarray(lengths) - 1, 1)[:, None]
    s = np.clip(np.arange(num_steps)[None, :] / span, 0.0, 1.0)  # [U, T]
    return start[:, None] + (end - start)[:, None] * s[..., None] ** power[:, None]


def _frame(problem: Problem, units: Padded):
    """``units``' valid rows as the front door's frame, and their ``(unit, time)``
    indexes."""
    model = problem.model
    u, t = np.nonzero(np.asarray(units.mask, bool))
    frame = pd.DataFrame(
        {
            **{n: units.w[u, t, i] for i, n in enumerate(model.condition_names)},
            **{n: units.x[u, t, i] for i, n in enumerate(problem.output_names)},
            "unit": units.unit_ids[u],
            "time": t,
        }
    )
    return frame, (u, t)


def front_ukf(problem: Problem, units: Padded, noise=None):
    """The front door's UKF on ``units``
    (:func:`jaxcal.calibrators.front.door.calibrate`) and the rows' ``(unit, time)``
    indexes."""
    frame, index = _frame(problem, units)
    result = calibrate(
        problem.model,
        frame,
        method="ukf",
        theta=list(problem.theta_names),
        outputs=list(problem.output_names),
        noise=noise,
        progress=False,
    )
    return result, index


def _time_basis(lengths: np.ndarray, num_steps: int) -> np.ndarray:
    """``[U, T, 3]`` the quadratic ``[1, s, s^2]`` in a unit's own time ``s = t /
    (L - 1)``, held at ``s = 1`` past its end."""
    span = np.maximum(np.asarray(lengths, np.float64) - 1.0, 1.0)
    s = np.minimum(np.arange(num_steps)[None, :] / span[:, None], 1.0)
    return np.stack([np.ones_like(s), s, s * s], axis=-1)


def estimated_drifts(problem: Problem, units: Padded) -> np.ndarray:
    """``[K, 3, P]`` the real units' own theta drifts: the UKF's theta on ``units``
    with the problem's noise, fitted per unit and parameter by a least-squares
    quadratic in the unit's own time (:func:`_time_basis`); the ``K`` units of at
    least three rows the UKF used.

    A band fitted on units whose parameters move as the real ones do (their drift
    rates, their levels) covers the real units about as often as it covers them;
    paths drawn across the whole box move faster than a slow wear, or stay
    constant, and the band comes out too wide for some parameters and too narrow
    for others (``results/policy_any_model``). The quadratic keeps the level and the
    drift and drops the filter's own noise and start-up transient.
    """
    noise = dict(zip(problem.output_names, problem.noise_std.tolist(), strict=True))
    result, (u, t) = front_ukf(problem, units, noise)
    num_units, num_steps = units.w.shape[:2]
    basis = _time_basis(units.lengths, num_steps)
    weight = np.zeros((num_units, num_steps))
    weight[u, t] = np.asarray(result.valid, np.float64)
    theta = np.zeros((num_units, num_steps, len(problem.theta_names)))
    theta[u, t] = np.nan_to_num(np.asarray(result.theta, np.float64))
    keep = weight.sum(axis=1) >= 3  # a quadratic needs three rows the UKF used
    if not keep.any():
        raise ValueError(
            "simulate.paths=data: the UKF used fewer than 3 rows of every training "
            "and validation unit, so the data show no drift; use simulate.paths=box"
        )
    basis, weight, theta = basis[keep], weight[keep], theta[keep]
    gram = np.einsum("uti,ut,utj->uij", basis, weight, basis)
    gram += 1e-9 * np.eye(3)  # three rows at nearly one time: still solvable
    return np.linalg.solve(gram, np.einsum("uti,ut,utp->uip", basis, weight, theta))


def drift_paths(
    problem: Problem, drifts: np.ndarray, lengths: np.ndarray, num_steps: int
) -> np.ndarray:
    """``[U, T, P]`` the drifts ``[K, 3, P]`` (:func:`estimated_drifts`) in turn
    (unit ``i`` follows drift ``i mod K``) along units of ``lengths``, clipped into
    the box."""
    pick = drifts[np.arange(len(lengths)) % len(drifts)]
    paths = np.einsum("uti,uip->utp", _time_basis(lengths, num_steps), pick)
    return np.clip(paths, problem.theta_low, problem.theta_high)
