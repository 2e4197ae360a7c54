"""Lyapunov actor-critic (Han et al. 2020), the paper's LAC ablation.

:func:`make_lac` returns an :class:`~jaxcal.agents.common.Agent` whose ``update`` does,
on one minibatch (paper Algorithm 1 without the CLAC term):

1. a Lyapunov critic step on J(L_c) with the target critic and target policy;
2. a policy step on eq. LAC against the updated critic;
3. a step on log(entropy temperature) (paper eq. temperature update) and on
   log(Lyapunov multiplier) (paper eq. gamma update), the latter projected onto
   (0, ``max_lyapunov_multiplier``];
4. the Polyak update of the target critic and target policy (tau).
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
    clip_log_multiplier,
    copy_tree,
    init_log_multiplier,
    init_optimized,
    make_act,
    minimize,
    polyak_update,
)
from jaxcal.agents.configs import LACConfig
from jaxcal.agents.networks import make_networks
from jaxcal.typedefs import Array, Metrics, PRNGKey, PyTree


@struct.dataclass
class LACState:
    """Everything LAC learns.

    Attributes:
        actor: policy parameters and Adam state.
        critic: Lyapunov critic parameters and Adam state.
        target_actor_params: Polyak-averaged policy (Algorithm 1's theta-bar).
        target_critic_params: Polyak-averaged Lyapunov critic (phi-bar_L).
        log_entropy_temperature: log of the paper's beta, with its Adam state.
        log_lyapunov_multiplier: log of the paper's lambda, with its Adam state.
        step: [] int32, number of updates done.
    """

    actor: Optimized
    critic: Optimized
    target_actor_params: PyTree
    target_critic_params: PyTree
    log_entropy_temperature: Optimized
    log_lyapunov_multiplier: Optimized
    step: Array


def make_lac(cfg: LACConfig, observation_size: int, action_size: int) -> Agent:
    """Builds the LAC agent.

    Args:
        cfg: hyperparameters (a :class:`CLACConfig` is refused: use ``make_clac``).
        observation_size: O.
        action_size: A.

    Returns:
        ``Agent(init, act, update, observation_size, action_size)``.
    """
    if type(cfg) is not LACConfig:
        raise ValueError(f"make_lac needs a LACConfig, got {type(cfg).__name__}")
    check_sizes(observation_size, action_size)
    networks = make_networks(cfg, action_size)
    actor_optimizer = optax.adam(cfg.actor_lr)
    critic_optimizer = optax.adam(cfg.critic_lr)
    temperature_optimizer = optax.adam(cfg.entropy_temperature_lr)
    multiplier_optimizer = optax.adam(cfg.lyapunov_multiplier_lr)
    target_entropy = cfg.resolved_target_entropy(action_size)

    def init(key: PRNGKey) -> LACState:
        key_actor, key_critic = jax.random.split(key)
        obs = jnp.zeros((1, observation_size), jnp.float32)
        action = jnp.zeros((1, action_size), jnp.float32)
        actor_params = networks.actor.init(key_actor, obs)
        critic_params = networks.critic.init(key_critic, obs, action)
        return LACState(
            actor=init_optimized(actor_optimizer, actor_params),
            critic=init_optimized(critic_optimizer, critic_params),
            target_actor_params=copy_tree(actor_params),
            target_critic_params=copy_tree(critic_params),
            log_entropy_temperature=init_log_multiplier(
                temperature_optimizer, cfg.initial_entropy_temperature
            ),
            log_lyapunov_multiplier=init_log_multiplier(
                multiplier_optimizer, cfg.initial_lyapunov_multiplier
            ),
            step=jnp.zeros((), jnp.int32),
        )

    def update(
        key: PRNGKey, state: LACState, batch: Transition
    ) -> tuple[LACState, Metrics]:
        key_critic, key_actor = jax.random.split(key)
        critic, critic_aux = minimize(
            critic_optimizer,
            state.critic,
            losses.lyapunov_critic_loss,
            state.target_critic_params,
            state.target_actor_params,
            batch,
            key_critic,
            networks,
            gamma=cfg.gamma,
        )
        actor, actor_aux = minimize(
            actor_optimizer,
            state.actor,
            losses.lac_actor_loss,
            critic.params,
            batch,
            key_actor,
            networks,
            entropy_temperature=jnp.exp(state.log_entropy_temperature.params),
            lyapunov_multiplier=jnp.exp(state.log_lyapunov_multiplier.params),
            alpha3=cfg.alpha3,
        )
        log_temperature, temperature_aux = minimize(
            temperature_optimizer,
            state.log_entropy_temperature,
            losses.entropy_temperature_loss,
            actor_aux["log_prob"],
            target_entropy,
        )
        log_multiplier, multiplier_aux = minimize(
            multiplier_optimizer,
            state.log_lyapunov_multiplier,
            losses.lyapunov_multiplier_loss,
            actor_aux["lyapunov_decrease"],
        )
        new_state = LACState(
            actor=actor,
            critic=critic,
            target_actor_params=polyak_update(
                state.target_actor_params, actor.params, cfg.tau
            ),
            target_critic_params=polyak_update(
                state.target_critic_params, critic.params, cfg.tau
            ),
            log_entropy_temperature=log_temperature,
            log_lyapunov_multiplier=clip_log_multiplier(
                log_multiplier, cfg.max_lyapunov_multiplier
            ),
            step=state.step + 1,
        )
        metrics = {**critic_aux, **actor_aux, **temperature_aux, **multiplier_aux}
        return new_state, metrics

    return Agent(init, make_act(networks.actor), update, observation_size, action_size)
