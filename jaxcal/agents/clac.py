"""Constrained Lyapunov actor-critic (CLAC), the paper's proposed learning algorithm.

CLAC is LAC (:mod:`jaxcal.agents.lac`) plus the action-smoothness term of paper
eq. CLAC, alpha E||pi*(s) - pi*(s_near)||, with s_near the next state of the same
transition. :func:`make_clac` returns an :class:`~jaxcal.agents.common.Agent` whose
``update`` does, on one minibatch (paper Algorithm 1):

1. a Lyapunov critic step on J(L_c) with the target critic and target policy;
2. a policy step on eq. CLAC against the updated critic;
3. steps on log(entropy temperature), log(Lyapunov multiplier) (clipped to
   (0, ``max_lyapunov_multiplier``]) and log(smoothness multiplier) (clipped to
   (0, ``max_smoothness_multiplier``]), the latter driving the mean action change
   towards ``smoothness_threshold``;
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
from jaxcal.agents.configs import CLACConfig
from jaxcal.agents.networks import make_networks
from jaxcal.typedefs import Array, Metrics, PRNGKey, PyTree


@struct.dataclass
class CLACState:
    """Everything CLAC learns.

    Attributes:
        actor: policy parameters and Adam state.
        critic: Lyapunov critic parameters and Adam state.
        target_actor_params: Polyak-averaged policy (Algorithm 1's theta-bar).
        target_critic_params: Polyak-averaged Lyapunov critic (phi-bar_L).
        log_entropy_temperature: log of the paper's beta, with its Adam state.
        log_lyapunov_multiplier: log of the paper's lambda, with its Adam state.
        log_smoothness_multiplier: log of the paper's alpha, with its Adam state.
        step: [] int32, number of updates done.
    """

    actor: Optimized
    critic: Optimized
    target_actor_params: PyTree
    target_critic_params: PyTree
    log_entropy_temperature: Optimized
    log_lyapunov_multiplier: Optimized
    log_smoothness_multiplier: Optimized
    step: Array


def make_clac(cfg: CLACConfig, observation_size: int, action_size: int) -> Agent:
    """Builds the CLAC agent.

    Args:
        cfg: hyperparameters.
        observation_size: O.
        action_size: A.

    Returns:
        ``Agent(init, act, update, observation_size, action_size)``.
    """
    if not isinstance(cfg, CLACConfig):
        raise ValueError(f"make_clac needs a CLACConfig, got {type(cfg).__name__}")
    check_sizes(observation_size, action_size)
    networks = make_networks(cfg, action_size)
    actor_optimizer = optax.adam(cfg.actor_lr)
    critic_optimizer = optax.adam(cfg.critic_lr)
    temperature_optimizer = optax.adam(cfg.entropy_temperature_lr)
    lyapunov_optimizer = optax.adam(cfg.lyapunov_multiplier_lr)
    smoothness_optimizer = optax.adam(cfg.smoothness_multiplier_lr)
    target_entropy = cfg.resolved_target_entropy(action_size)

    def init(key: PRNGKey) -> CLACState:
        key_actor, key_critic = jax.random.split(key)
        obs = jnp.zeros((1, observation_size), jnp.float32)
        action = jnp.zeros((1, action_size), jnp.float32)
        actor_params = networks.actor.init(key_actor, obs)
        critic_params = networks.critic.init(key_critic, obs, action)
        return CLACState(
            actor=init_optimized(actor_optimizer, actor_params),
            critic=init_optimized(critic_optimizer, critic_params),
            target_actor_params=copy_tree(actor_params),
            target_critic_params=copy_tree(critic_params),
            log_entropy_temperature=init_log_multiplier(
                temperature_optimizer, cfg.initial_entropy_temperature
            ),
            log_lyapunov_multiplier=init_log_multiplier(
                lyapunov_optimizer, cfg.initial_lyapunov_multiplier
            ),
            log_smoothness_multiplier=init_log_multiplier(
                smoothness_optimizer, cfg.initial_smoothness_multiplier
            ),
            step=jnp.zeros((), jnp.int32),
        )

    def update(
        key: PRNGKey, state: CLACState, batch: Transition
    ) -> tuple[CLACState, Metrics]:
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
            losses.clac_actor_loss,
            critic.params,
            batch,
            key_actor,
            networks,
            entropy_temperature=jnp.exp(state.log_entropy_temperature.params),
            lyapunov_multiplier=jnp.exp(state.log_lyapunov_multiplier.params),
            smoothness_multiplier=jnp.exp(state.log_smoothness_multiplier.params),
            alpha3=cfg.alpha3,
        )
        log_temperature, temperature_aux = minimize(
            temperature_optimizer,
            state.log_entropy_temperature,
            losses.entropy_temperature_loss,
            actor_aux["log_prob"],
            target_entropy,
        )
        log_lyapunov, lyapunov_aux = minimize(
            lyapunov_optimizer,
            state.log_lyapunov_multiplier,
            losses.lyapunov_multiplier_loss,
            actor_aux["lyapunov_decrease"],
        )
        log_smoothness, smoothness_aux = minimize(
            smoothness_optimizer,
            state.log_smoothness_multiplier,
            losses.smoothness_multiplier_loss,
            actor_aux["action_change"],
            cfg.smoothness_threshold,
        )
        new_state = CLACState(
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
                log_lyapunov, cfg.max_lyapunov_multiplier
            ),
            log_smoothness_multiplier=clip_log_multiplier(
                log_smoothness, cfg.max_smoothness_multiplier
            ),
            step=state.step + 1,
        )
        metrics = {
            **critic_aux,
            **actor_aux,
            **temperature_aux,
            **lyapunov_aux,
            **smoothness_aux,
        }
        return new_state, metrics

    return Agent(init, make_act(networks.actor), update, observation_size, action_size)
