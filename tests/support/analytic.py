"""A small analytic calibration problem with a known answer, for tests and smoke runs.

The "physics" is x = F(w, theta) = A w + B theta + c + kappa (A w) * (B theta), linear
for kappa = 0 and mildly nonlinear otherwise (the sensitivity to theta then depends on
the operating point, as in an engine). Operating conditions w are smooth random signals
(sums of sinusoids); each unit's theta drifts slowly and monotonically inside [0.1, 0.9]
of a unit box, like a degradation. Units are padded to a common length with zeros after
their own (random) length, exercising the masking of every consumer.

Optimal calibration is known in closed form here (theta = B^+ (x - A w - c) for
kappa = 0), so a learner can be judged by its theta RMSE against the truth.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from jaxcal.envs.tracking import make_env_params
from jaxcal.problem import Normalisation
from jaxcal.typedefs import Array, PRNGKey
from support.norm import own_norm


@struct.dataclass
class LinearModelParams:
    """Parameters of the analytic model F.

    Attributes:
        a: [S, W] sensitivity to the operating conditions.
        b: [S, P] sensitivity to the calibrated parameters.
        c: [S] offset.
        interaction: [] kappa, weight of the (A w) * (B theta) term.
    """

    a: Array
    b: Array
    c: Array
    interaction: Array


def analytic_dynamics(
    params: LinearModelParams, w_next: Array, xhat: Array, theta: Array
) -> Array:
    """x-hat_{t+1} = F(w_{t+1}, theta_{t+1}); like the physics, ignores x-hat_t.

    Args:
        params: model parameters.
        w_next: [W]; xhat: [S] (unused); theta: [P].

    Returns:
        [S] model output.
    """
    del xhat
    aw = params.a @ w_next
    btheta = params.b @ theta
    return aw + btheta + params.c + params.interaction * aw * btheta


class AnalyticProblem(NamedTuple):
    """A generated fleet and its model.

    Attributes:
        dyn_params: the model parameters (pass with :func:`analytic_dynamics`).
        w: [U, T, W] operating conditions, zero after ``lengths``.
        x: [U, T, S] observations F(w, theta) (+ noise), zero after ``lengths``.
        theta: [U, T, P] true parameters, zero after ``lengths``.
        lengths: [U] int32 valid rows per unit.
        theta_low, theta_high: [P] action box (here [0, 1]).
    """

    dyn_params: LinearModelParams
    w: Array
    x: Array
    theta: Array
    lengths: Array
    theta_low: Array
    theta_high: Array


def _smooth_signals(key: PRNGKey, shape: tuple[int, int, int]) -> Array:
    """Sum of three random sinusoids per (unit, channel), ~unit amplitude: [U, T, W]."""
    num_units, num_steps, dim = shape
    key_freq, key_phase, key_amp = jax.random.split(key, 3)
    freq = jax.random.uniform(key_freq, (num_units, 1, dim, 3), minval=0.5, maxval=4.0)
    phase = jax.random.uniform(key_phase, (num_units, 1, dim, 3), maxval=2 * jnp.pi)
    amp = jax.random.uniform(key_amp, (num_units, 1, dim, 3), minval=0.3, maxval=0.8)
    t = jnp.linspace(0.0, 1.0, num_steps)[None, :, None, None]
    return jnp.sum(amp * jnp.sin(2 * jnp.pi * freq * t + phase), axis=-1)


def make_analytic_problem(
    key: PRNGKey,
    *,
    num_units: int = 8,
    num_steps: int = 200,
    condition_dim: int = 2,
    sensor_dim: int = 4,
    param_dim: int = 1,
    interaction: float = 0.0,
    noise_std: float = 0.0,
    min_length: int | None = None,
) -> AnalyticProblem:
    """Generates a fleet of units of the analytic model.

    Args:
        key: PRNG key.
        num_units: U.
        num_steps: T, padded length.
        condition_dim, sensor_dim, param_dim: W, S, P.
        interaction: kappa (0 gives a linear model).
        noise_std: std of Gaussian noise added to x (physical units).
        min_length: shortest unit; ``None`` makes every unit ``num_steps`` long.

    Returns:
        :class:`AnalyticProblem`.
    """
    if min_length is None:
        min_length = num_steps
    if not 2 <= min_length <= num_steps:
        raise ValueError(f"min_length must lie in [2, num_steps={num_steps}]")
    keys = jax.random.split(key, 8)
    dyn_params = LinearModelParams(
        a=jax.random.normal(keys[0], (sensor_dim, condition_dim)),
        b=jax.random.normal(keys[1], (sensor_dim, param_dim)),
        c=jax.random.normal(keys[2], (sensor_dim,)),
        interaction=jnp.asarray(interaction, dtype=jnp.result_type(float)),
    )
    w = _smooth_signals(keys[3], (num_units, num_steps, condition_dim))
    start = jax.random.uniform(
        keys[4], (num_units, 1, param_dim), minval=0.1, maxval=0.5
    )
    drift = jax.random.uniform(
        keys[5], (num_units, 1, param_dim), minval=0.1, maxval=0.4
    )
    progress = jnp.linspace(0.0, 1.0, num_steps)[None, :, None] ** 2
    theta = start + drift * progress
    per_step = jax.vmap(analytic_dynamics, in_axes=(None, 0, None, 0))
    x = jax.vmap(per_step, in_axes=(None, 0, None, 0))(
        dyn_params, w, jnp.zeros(sensor_dim), theta
    )
    x = x + noise_std * jax.random.normal(keys[6], x.shape)
    lengths = jax.random.randint(keys[7], (num_units,), min_length, num_steps + 1)
    valid = (jnp.arange(num_steps)[None, :] < lengths[:, None])[..., None]
    return AnalyticProblem(
        dyn_params=dyn_params,
        w=jnp.where(valid, w, 0.0),
        x=jnp.where(valid, x, 0.0),
        theta=jnp.where(valid, theta, 0.0),
        lengths=lengths.astype(jnp.int32),
        theta_low=jnp.zeros(param_dim),
        theta_high=jnp.ones(param_dim),
    )


def problem_env_params(
    problem: AnalyticProblem, units: slice | Array, stats: Normalisation | None = None
):
    """:class:`~jaxcal.envs.tracking.EnvParams` of a subset of the problem's units.

    Args:
        problem: the generated fleet.
        units: a slice or an index array selecting units.
        stats: normalisation statistics (``None``: those of the selected units; pass
            the training units' statistics for held-out units).

    Returns:
        EnvParams for the tracking environment with :func:`analytic_dynamics`.
    """
    return make_env_params(
        problem.w[units],
        problem.x[units],
        problem.lengths[units],
        problem.theta_low,
        problem.theta_high,
        problem.dyn_params,
        stats=own_norm(problem.w[units], problem.x[units], problem.lengths[units])
        if stats is None
        else stats,
    )
