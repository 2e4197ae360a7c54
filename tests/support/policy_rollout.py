"""The trained policy's deterministic rollout over whole unit trajectories.

:func:`evaluate_policy` runs pi*(s) = tanh(mean) through every unit of the tracking
environment from its first sample (``lax.scan`` over time, ``vmap`` over units), the
reference the deployment calibrator
(:mod:`jaxcal.calibrators.methods.policy.calibrator`) reproduces on
samples t >= 1 (tests only).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.agents.common import Agent
from jaxcal.envs.tracking import Env, EnvParams
from jaxcal.typedefs import Array, PRNGKey


class EvalOutput(NamedTuple):
    """Deterministic-policy rollout over whole unit trajectories.

    Attributes:
        theta: [U, T, P] inferred parameters; theta[:, t] is the action taken at t - 1,
            and theta[:, 0] repeats theta[:, 1] (no action precedes the first sample).
        xhat: [U, T, S] model output, xhat[:, 0] = x[:, 0].
        cost: [U, T] tracking cost c_{t-1} of reaching xhat[:, t]; cost[:, 0] = 0.
        mask: [U, T] bool, t < lengths[u]; every output is 0 where the mask is False.
    """

    theta: Array
    xhat: Array
    cost: Array
    mask: Array


def evaluate_policy(
    key: PRNGKey, env: Env, agent: Agent, agent_state: Any, env_params: EnvParams
) -> EvalOutput:
    """Runs pi*(s) = tanh(mean) through each unit from its first sample (paper §4).

    ``lax.scan`` over time, ``vmap`` over units; padded rows are masked out. Jit it at
    the call site (``jax.jit(evaluate_policy, static_argnums=(1, 2))``).

    Args:
        key: PRNG key (the deterministic policy and the env do not consume randomness,
            but the interfaces take keys).
        env: the tracking environment.
        agent: the trained agent.
        agent_state: its state.
        env_params: the units to run through (use the training normalisation).

    Returns:
        :class:`EvalOutput`.
    """
    num_units, num_steps = env_params.x.shape[:2]

    def run_unit(key_unit: PRNGKey, unit: Array):
        obs, state = env.reset_at(env_params, unit, 0)
        xhat_first = state.xhat

        def body(carry, key_t):
            obs, state = carry
            key_act, key_step = jax.random.split(key_t)
            action = agent.act(key_act, agent_state, obs, deterministic=True)
            obs, state, cost, _, info = env.step(key_step, state, action, env_params)
            return (obs, state), (info["theta"], state.xhat, cost)

        keys = jax.random.split(key_unit, num_steps - 1)
        _, (theta, xhat, cost) = jax.lax.scan(body, (obs, state), keys)
        if env.config.incremental:  # the step at t returns theta_t (predict-correct)
            theta = jnp.concatenate([theta, theta[-1:]])
        else:  # the step at t sets the theta of sample t + 1
            theta = jnp.concatenate([theta[:1], theta])
        xhat = jnp.concatenate([xhat_first[None], xhat])
        cost = jnp.concatenate([jnp.zeros((1,), cost.dtype), cost])
        mask = jnp.arange(num_steps) < env_params.lengths[unit]
        return EvalOutput(
            theta=jnp.where(mask[:, None], theta, 0.0),
            xhat=jnp.where(mask[:, None], xhat, 0.0),
            cost=jnp.where(mask, cost, 0.0),
            mask=mask,
        )

    keys = jax.random.split(key, num_units)
    return jax.vmap(run_unit)(keys, jnp.arange(num_units))
