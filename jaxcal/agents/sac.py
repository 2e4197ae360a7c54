"""Soft actor-critic on costs (Haarnoja et al. 2018) with twin Q critics.

The comparison baseline of the paper's learning algorithms: the same policy network and
entropy-temperature adaptation as LAC/CLAC, but a twin soft-Q critic instead of the
Lyapunov critic. :func:`make_sac` returns an :class:`~jaxcal.agents.common.Agent`; its
``update`` does, on one minibatch, a critic step, an actor step (against the updated
critic), a temperature step and the Polyak update of the target critics.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax
from flax import struct

from jaxcal.agents import losses
from jaxcal.agents.buffer import Transition
from jaxcal.agents.common import (
    Agent,
    Optimized,
    check_sizes,
    copy_tree,
    init_log_multiplier,
    init_optimized,
    make_act,
    minimize,
    polyak_update,
)
from jaxcal.agents.configs import SACConfig
from jaxcal.agents.networks import make_networks
from jaxcal.typedefs import Array, Metrics, PRNGKey, PyTree


@struct.dataclass
class SACState:
    """Everything SAC learns.

    Attributes:
        actor: policy parameters and Adam state.
        critic: twin-Q parameters (leading ensemble axis) and Adam state.
        target_critic_params: Polyak-averaged critic parameters.
        log_entropy_temperature: log beta (the paper's beta) and its Adam state.
        step: [] int32, number of updates done.
    """

    actor: Optimized
    critic: Optimized
    target_critic_params: PyTree
    log_entropy_temperature: Optimized
    step: Array


def make_sac(cfg: SACConfig, observation_size: int, action_size: int) -> Agent:
    """Builds the SAC agent.

    Args:
        cfg: hyperparameters.
        observation_size: O.
        action_size: A.

    Returns:
        ``Agent(init, act, update, observation_size, action_size)``.
    """
    if not isinstance(cfg, SACConfig):
        raise ValueError(f"make_sac needs a SACConfig, got {type(cfg).__name__}")
    check_sizes(observation_size, action_size)
    networks = make_networks(cfg, action_size)
    actor_optimizer = optax.adam(cfg.actor_lr)
    critic_optimizer = optax.adam(cfg.critic_lr)
    temperature_optimizer = optax.adam(cfg.entropy_temperature_lr)
    target_entropy = cfg.resolved_target_entropy(action_size)

    def init(key: PRNGKey) -> SACState:
        key_actor, key_critic = jax.random.split(key)
        obs = jnp.zeros((1, observation_size), jnp.float32)
        action = jnp.zeros((1, action_size), jnp.float32)
        actor_params = networks.actor.init(key_actor, obs)
        critic_params = networks.critic.init(key_critic, obs, action)
        return SACState(
            actor=init_optimized(actor_optimizer, actor_params),
            critic=init_optimized(critic_optimizer, critic_params),
            target_critic_params=copy_tree(critic_params),
            log_entropy_temperature=init_log_multiplier(
                temperature_optimizer, cfg.initial_entropy_temperature
            ),
            step=jnp.zeros((), jnp.int32),
        )

    def update(
        key: PRNGKey, state: SACState, batch: Transition
    ) -> tuple[SACState, Metrics]:
        key_critic, key_actor = jax.random.split(key)
        temperature = jnp.exp(state.log_entropy_temperature.params)
        critic, critic_aux = minimize(
            critic_optimizer,
            state.critic,
            losses.soft_q_critic_loss,
            state.target_critic_params,
            state.actor.params,
            batch,
            key_critic,
            networks,
            gamma=cfg.gamma,
            entropy_temperature=temperature,
        )
        actor, actor_aux = minimize(
            actor_optimizer,
            state.actor,
            losses.sac_actor_loss,
            critic.params,
            batch,
            key_actor,
            networks,
            entropy_temperature=temperature,
        )
        log_temperature, temperature_aux = minimize(
            temperature_optimizer,
            state.log_entropy_temperature,
            losses.entropy_temperature_loss,
            actor_aux["log_prob"],
            target_entropy,
        )
        new_state = SACState(
            actor=actor,
            critic=critic,
            target_critic_params=polyak_update(
                state.target_critic_params, critic.params, cfg.tau
            ),
            log_entropy_temperature=log_temperature,
            step=state.step + 1,
        )
        return new_state, {**critic_aux, **actor_aux, **temperature_aux}

    return Agent(init, make_act(networks.actor), update, observation_size, action_size)
