"""Training runner: env steps and agent updates advanced in ``lax.scan`` chunks.

One iteration = one step of ``num_envs`` parallel environments (vmapped, random actions
during warm-up, policy samples afterwards), the transitions written to the on-device
replay buffer, finished episodes reset (gymnax-style auto-reset) and
``updates_per_step`` agent updates on minibatches from the buffer once it holds
``min_buffer_size`` transitions (``lax.cond``, no Python branching on traced values).
:func:`make_train_chunk` scans ``num_steps_per_chunk`` iterations; the host only jits it
once (``donate_argnums=0``) and logs between chunks::

    train_chunk = jax.jit(make_train_chunk(env, agent, cfg), donate_argnums=0)
    runner = init_runner(key, env, agent, env_params, cfg)
    for _ in range(num_chunks):
        runner, metrics = train_chunk(runner, env_params)

The environment parameters (data, normalisation, dynamics parameters) are an argument of
the chunk rather than part of the runner state: they are not donated, not duplicated
when vmapping over seeds (``in_axes=(0, None)``), and a new data set or surrogate does
not trigger recompilation.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from jaxcal.agents.buffer import (
    ReplayBuffer,
    Transition,
    add_transitions,
    init_buffer,
    sample_transitions,
)
from jaxcal.agents.common import Agent
from jaxcal.envs.tracking import Env, EnvParams, check_env_params
from jaxcal.typedefs import Array, Metrics, PRNGKey


@dataclasses.dataclass(frozen=True)
class RunnerConfig:
    """Static configuration of the training loop.

    Attributes:
        num_envs: B, parallel environments stepped per iteration.
        num_steps_per_chunk: iterations per jitted chunk (host logs between chunks).
        updates_per_step: agent updates per iteration (each on a fresh minibatch).
        batch_size: minibatch size (paper appendix: 256).
        buffer_size: replay capacity in transitions.
        warmup_steps: env transitions (counted over all envs) taken with uniform
            random actions before the policy acts.
        min_buffer_size: transitions in the buffer before updates start (at least
            ``batch_size`` is enforced).
    """

    num_envs: int = 16
    num_steps_per_chunk: int = 1000
    updates_per_step: int = 1
    batch_size: int = 256
    buffer_size: int = 1_000_000
    warmup_steps: int = 10_000
    min_buffer_size: int = 10_000

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            low = 0 if field.name in ("warmup_steps", "min_buffer_size") else 1
            if not isinstance(value, int) or value < low:
                raise ValueError(
                    f"RunnerConfig.{field.name} must be an int >= {low}, got {value!r}"
                )
        if self.buffer_size < self.num_envs:
            raise ValueError("RunnerConfig.buffer_size must be >= num_envs")

    @property
    def update_threshold(self) -> int:
        """Buffer size from which updates run: max(min_buffer_size, batch_size)."""
        return max(self.min_buffer_size, self.batch_size)


@struct.dataclass
class RunnerState:
    """Everything a training run carries from one iteration to the next.

    Attributes:
        env_state: batched env states, leading axis ``[B]``.
        obs: [B, O] current observations.
        agent_state: the agent's state (``SACState``, ``LACState`` or ``CLACState``).
        buffer: the replay buffer.
        key: PRNG key, split every iteration.
        env_steps: [] int32, transitions collected so far (all envs).
        num_updates: [] int32, agent updates done so far.
        episode_cost: [B] summed cost of each env's current episode.
    """

    env_state: Any
    obs: Array
    agent_state: Any
    buffer: ReplayBuffer
    key: PRNGKey
    env_steps: Array
    num_updates: Array
    episode_cost: Array


def init_runner(
    key: PRNGKey, env: Env, agent: Agent, env_params: EnvParams, cfg: RunnerConfig
) -> RunnerState:
    """Initial runner state: fresh agent, empty buffer, ``num_envs`` reset envs.

    Raises:
        ValueError: if the params do not fit the env (see
            :func:`~jaxcal.envs.tracking.check_env_params`) or the agent's sizes differ
            from the env's.
    """
    if env.observation_size != agent.observation_size:
        raise ValueError(
            f"agent observation_size {agent.observation_size} != env "
            f"observation_size {env.observation_size}"
        )
    if env.action_size != agent.action_size:
        raise ValueError(
            f"agent action_size {agent.action_size} != env action_size "
            f"{env.action_size}"
        )
    check_env_params(env_params, env.config)
    # key_agent as initial_agent_state derives it
    key_agent, key_reset, key_run = jax.random.split(key, 3)
    keys_reset = jax.random.split(key_reset, cfg.num_envs)
    obs, env_state = jax.vmap(env.reset, in_axes=(0, None))(keys_reset, env_params)
    return RunnerState(
        env_state=env_state,
        obs=obs,
        agent_state=agent.init(key_agent),
        buffer=init_buffer(cfg.buffer_size, env.observation_size, env.action_size),
        key=key_run,
        env_steps=jnp.zeros((), jnp.int32),
        num_updates=jnp.zeros((), jnp.int32),
        episode_cost=jnp.zeros((cfg.num_envs,), jnp.float32),
    )


def initial_agent_state(key: PRNGKey, agent: Agent):
    """The agent state a new runner of ``key`` starts with (:func:`init_runner`'s),
    without its buffer and environments: the untrained policy, scored after a
    training whose chunk 0 was not (``jaxcal.training.kept_policy``)."""
    return agent.init(jax.random.split(key, 3)[0])


def _where_done(done: Array, reset_value: Array, value: Array) -> Array:
    return jnp.where(
        done.reshape(done.shape + (1,) * (value.ndim - 1)), reset_value, value
    )


def make_train_chunk(
    env: Env, agent: Agent, cfg: RunnerConfig
) -> Callable[[RunnerState, EnvParams], tuple[RunnerState, Metrics]]:
    """Builds the pure ``train_chunk(runner_state, env_params) -> (state, metrics)``.

    Metrics (scalars):

    * ``cost``: mean cost per env step over the chunk;
    * ``episode_cost``: mean summed cost of the episodes finished in the chunk (0 if
      none) and ``episodes``, their number;
    * the agent's update metrics, averaged over the iterations that updated;
    * the counters ``env_steps``, ``num_updates`` and ``buffer_size`` at chunk end.
    """
    iteration = _make_iteration(env, agent, cfg)

    def train_chunk(
        runner: RunnerState, env_params: EnvParams
    ) -> tuple[RunnerState, Metrics]:
        runner, steps = jax.lax.scan(
            lambda r, _: iteration(r, env_params),
            runner,
            None,
            length=cfg.num_steps_per_chunk,
        )
        return runner, _chunk_metrics(steps, runner)

    return train_chunk


def _make_updates(agent: Agent, cfg: RunnerConfig):
    """``(run_updates, skip_updates)``, both ``(agent_state, buffer, key) ->
    (agent_state, metrics)``: ``updates_per_step`` agent updates on fresh minibatches
    (metrics averaged), or none with zero metrics of the same shapes (the other
    branch of the ``lax.cond`` on the buffer's size)."""

    def run_updates(agent_state: Any, buffer: ReplayBuffer, key: PRNGKey):
        def one_update(state, key_update):
            key_sample, key_agent = jax.random.split(key_update)
            batch = sample_transitions(key_sample, buffer, cfg.batch_size)
            return agent.update(key_agent, state, batch)

        keys = jax.random.split(key, cfg.updates_per_step)
        agent_state, metrics = jax.lax.scan(one_update, agent_state, keys)
        return agent_state, jax.tree.map(jnp.mean, metrics)

    def skip_updates(agent_state: Any, buffer: ReplayBuffer, key: PRNGKey):
        shapes = jax.eval_shape(run_updates, agent_state, buffer, key)[1]
        return agent_state, jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

    return run_updates, skip_updates


def _make_iteration(env: Env, agent: Agent, cfg: RunnerConfig):
    """``iteration(runner, env_params) -> (runner, step metrics)``: one step of the
    ``num_envs`` environments (uniform random actions during warm-up, policy samples
    afterwards), the transitions written to the buffer, finished episodes reset and
    the agent updated once the buffer holds ``update_threshold`` transitions."""
    step_envs = jax.vmap(env.step, in_axes=(0, 0, 0, None))
    reset_envs = jax.vmap(env.reset, in_axes=(0, None))
    run_updates, skip_updates = _make_updates(agent, cfg)

    def iteration(runner: RunnerState, env_params: EnvParams):
        key, key_act, key_random, key_step, key_reset, key_update = jax.random.split(
            runner.key, 6
        )
        policy_action = agent.act(key_act, runner.agent_state, runner.obs)
        random_action = jax.random.uniform(
            key_random, policy_action.shape, policy_action.dtype, -1.0, 1.0
        )
        is_warmup = runner.env_steps < cfg.warmup_steps
        action = jnp.where(is_warmup, random_action, policy_action)
        keys_step = jax.random.split(key_step, cfg.num_envs)
        next_obs, next_env_state, cost, done, info = step_envs(
            keys_step, runner.env_state, action, env_params
        )
        transition = Transition(
            obs=runner.obs,
            action=action,
            cost=cost,
            next_obs=next_obs,
            terminal=info["terminated"].astype(jnp.float32),
        )
        buffer = add_transitions(runner.buffer, transition)
        # Resets only on iterations where an episode ends (episodes of equal length
        # end together): a reset may evaluate the model (incremental actions predict
        # the first sample), which would otherwise double the cost of every step.
        reset_obs, reset_env_state = jax.lax.cond(
            jnp.any(done),
            lambda: reset_envs(jax.random.split(key_reset, cfg.num_envs), env_params),
            lambda: (next_obs, next_env_state),
        )
        env_state = jax.tree.map(
            lambda r, n: _where_done(done, r, n), reset_env_state, next_env_state
        )
        episode_cost = runner.episode_cost + cost
        can_update = buffer.size >= cfg.update_threshold
        agent_state, update_metrics = jax.lax.cond(
            can_update,
            run_updates,
            skip_updates,
            runner.agent_state,
            buffer,
            key_update,
        )
        new_runner = RunnerState(
            env_state=env_state,
            obs=_where_done(done, reset_obs, next_obs),
            agent_state=agent_state,
            buffer=buffer,
            key=key,
            env_steps=runner.env_steps + cfg.num_envs,
            num_updates=runner.num_updates + can_update * cfg.updates_per_step,
            episode_cost=jnp.where(done, 0.0, episode_cost),
        )
        step_metrics = {
            "cost": cost.mean(),
            "finished_cost": jnp.sum(jnp.where(done, episode_cost, 0.0)),
            "finished": jnp.sum(done),
            "updated": can_update,
            "update": update_metrics,
        }
        return new_runner, step_metrics

    return iteration


def _chunk_metrics(steps: dict, runner: RunnerState) -> Metrics:
    """The chunk's metrics from its iterations' ``steps`` (stacked over the scan) and
    the runner at its end: the update metrics averaged over the iterations that
    updated, the mean cost, the finished episodes' mean cost and count, and the
    counters."""
    updated = steps["updated"].astype(jnp.float32)
    num_updated = jnp.maximum(updated.sum(), 1.0)
    metrics = {
        name: jnp.sum(values * updated) / num_updated
        for name, values in steps["update"].items()
    }
    episodes = steps["finished"].sum()
    metrics.update(
        cost=steps["cost"].mean(),
        episode_cost=steps["finished_cost"].sum() / jnp.maximum(episodes, 1),
        episodes=episodes,
        env_steps=runner.env_steps,
        num_updates=runner.num_updates,
        buffer_size=runner.buffer.size,
    )
    return metrics
