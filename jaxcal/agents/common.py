"""Pieces shared by the SAC, LAC and CLAC agents.

* :class:`Agent`: the interface every agent factory returns, a NamedTuple of pure
  functions ``init``, ``act`` and ``update`` (optax/brax pattern).
* :class:`Optimized`: minimal pytree of ``params`` + ``opt_state`` for one optimised
  quantity (a network or a log-multiplier); the optimiser itself is closed over by the
  factory, so no callable ends up in the agent state.
* :func:`minimize`, :func:`polyak_update`, :func:`init_log_multiplier`,
  :func:`make_act`: small helpers the agents compose.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from jaxcal.agents.buffer import Transition
from jaxcal.agents.networks import (
    SquashedGaussianActor,
    deterministic_action,
    sample_squashed_gaussian,
)
from jaxcal.typedefs import Array, Metrics, PRNGKey, PyTree


class Agent(NamedTuple):
    """An RL agent as three pure functions.

    Attributes:
        init: ``init(key) -> agent_state``.
        act: ``act(key, agent_state, obs [..., O], deterministic=False) -> action
            [..., A]`` in [-1, 1]; ``deterministic=True`` gives tanh(mean).
        update: ``update(key, agent_state, batch: Transition) -> (agent_state,
            metrics)``, one gradient step on critic, actor and multipliers.
        observation_size: O.
        action_size: A.
    """

    init: Callable[[PRNGKey], Any]
    act: Callable[..., Array]
    update: Callable[[PRNGKey, Any, Transition], tuple[Any, Metrics]]
    observation_size: int
    action_size: int


@struct.dataclass
class Optimized:
    """Parameters and their optimiser state (the optimiser is closed over elsewhere)."""

    params: PyTree
    opt_state: PyTree


def init_optimized(
    optimizer: optax.GradientTransformation, params: PyTree
) -> Optimized:
    """Pairs ``params`` with a fresh optimiser state."""
    return Optimized(params=params, opt_state=optimizer.init(params))


def minimize(
    optimizer: optax.GradientTransformation,
    state: Optimized,
    loss_fn: Callable[..., tuple[Array, Metrics]],
    *args: Any,
    **kwargs: Any,
) -> tuple[Optimized, Metrics]:
    """One optimiser step on ``loss_fn(state.params, *args, **kwargs) -> (loss, aux)``:
    ``params <- params + optimizer.update(grads)``; returns ``(new_state, aux)``."""
    grads, aux = jax.grad(loss_fn, has_aux=True)(state.params, *args, **kwargs)
    updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
    return Optimized(optax.apply_updates(state.params, updates), opt_state), aux


def copy_tree(tree: PyTree) -> PyTree:
    """Fresh device buffers for every leaf.

    Targets start equal to the online networks; giving them their own buffers lets the
    runner state be donated to ``jax.jit`` (a buffer cannot be donated twice).
    """
    return jax.tree.map(jnp.copy, tree)


def polyak_update(target: PyTree, online: PyTree, tau: float) -> PyTree:
    """Soft update ``target <- tau * online + (1 - tau) * target`` (Algorithm 1)."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def init_log_multiplier(
    optimizer: optax.GradientTransformation, initial_value: float
) -> Optimized:
    """A positive multiplier stored as its float32 log, with its optimiser state."""
    return init_optimized(optimizer, jnp.asarray(math.log(initial_value), jnp.float32))


def clip_log_multiplier(state: Optimized, max_value: float) -> Optimized:
    """Projects ``exp(log_value)`` onto (0, max_value] after a gradient step.

    Projecting the logarithm (rather than clipping ``exp`` at use, as the reference code
    does) keeps the multiplier responsive: the log value cannot drift far above the clip
    where its gradient would have to undo the drift before the multiplier moves again.
    """
    return state.replace(params=jnp.minimum(state.params, math.log(max_value)))


def make_act(actor: SquashedGaussianActor) -> Callable[..., Array]:
    """Builds ``act(key, agent_state, obs, deterministic=False)`` for any agent state
    with an ``actor: Optimized`` field."""

    def act(
        key: PRNGKey, agent_state: Any, obs: Array, deterministic: bool = False
    ) -> Array:
        mean, log_std = actor.apply(agent_state.actor.params, obs)
        if deterministic:
            return deterministic_action(mean)
        action, _ = sample_squashed_gaussian(key, mean, log_std)
        return action

    return act


def check_sizes(observation_size: int, action_size: int) -> None:
    """Raises ValueError unless both sizes are positive ints."""
    for name, value in (
        ("observation_size", observation_size),
        ("action_size", action_size),
    ):
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
