"""The shared actor-critic update: Algorithm 1's order, and the spec's checks."""

import functools

import chex
import jax
import jax.numpy as jnp
import optax
import pytest

from jaxcal.agents import losses
from jaxcal.agents.actor_critic import ActorCriticSpec, make_actor_critic
from jaxcal.agents.buffer import Transition
from jaxcal.agents.clac import make_clac
from jaxcal.agents.common import clip_log_multiplier, minimize, polyak_update
from jaxcal.agents.configs import CLACConfig, LACConfig
from jaxcal.agents.lac import LACState, lac_critic_loss
from jaxcal.agents.networks import make_networks

OBS, ACT, B = 6, 2, 16
CFG = CLACConfig(actor_hidden_sizes=(8, 8), critic_hidden_sizes=(8, 8))


def _batch(key):
    keys = jax.random.split(key, 4)
    return Transition(
        obs=jax.random.normal(keys[0], (B, OBS), jnp.float32),
        action=jax.random.uniform(keys[1], (B, ACT), jnp.float32, -1.0, 1.0),
        cost=jax.random.uniform(keys[2], (B,), jnp.float32),
        next_obs=jax.random.normal(keys[3], (B, OBS), jnp.float32),
        terminal=jnp.zeros((B,), jnp.float32),
    )


def _clac_update_by_hand(key, state, batch):
    """Algorithm 1 for CLAC spelled out step by step with the losses."""
    networks = make_networks(CFG, ACT)
    key_critic, key_actor = jax.random.split(key)
    critic, _ = minimize(
        optax.adam(CFG.critic_lr),
        state.critic,
        losses.lyapunov_critic_loss,
        state.target_critic_params,
        state.target_actor_params,
        batch,
        key_critic,
        networks,
        gamma=CFG.gamma,
    )
    # The policy steps against the updated critic, with the old multipliers.
    actor, aux = minimize(
        optax.adam(CFG.actor_lr),
        state.actor,
        losses.clac_actor_loss,
        critic.params,
        batch,
        key_actor,
        networks,
        entropy_temperature=jnp.exp(state.log_entropy_temperature.params),
        lyapunov_multiplier=jnp.exp(state.log_lyapunov_multiplier.params),
        smoothness_multiplier=jnp.exp(state.log_smoothness_multiplier.params),
        alpha3=CFG.alpha3,
    )
    temperature, _ = minimize(
        optax.adam(CFG.entropy_temperature_lr),
        state.log_entropy_temperature,
        losses.entropy_temperature_loss,
        aux["log_prob"],
        CFG.resolved_target_entropy(ACT),
    )
    lyapunov, _ = minimize(
        optax.adam(CFG.lyapunov_multiplier_lr),
        state.log_lyapunov_multiplier,
        losses.lyapunov_multiplier_loss,
        aux["lyapunov_decrease"],
    )
    smoothness, _ = minimize(
        optax.adam(CFG.smoothness_multiplier_lr),
        state.log_smoothness_multiplier,
        losses.smoothness_multiplier_loss,
        aux["action_change"],
        CFG.smoothness_threshold,
    )
    return state.replace(
        actor=actor,
        critic=critic,
        target_actor_params=polyak_update(
            state.target_actor_params, actor.params, CFG.tau
        ),
        target_critic_params=polyak_update(
            state.target_critic_params, critic.params, CFG.tau
        ),
        log_entropy_temperature=temperature,
        log_lyapunov_multiplier=clip_log_multiplier(
            lyapunov, CFG.max_lyapunov_multiplier
        ),
        log_smoothness_multiplier=clip_log_multiplier(
            smoothness, CFG.max_smoothness_multiplier
        ),
        step=state.step + 1,
    )


def test_shared_update_equals_algorithm_1_spelled_out():
    agent = make_clac(CFG, OBS, ACT)
    state = agent.init(jax.random.key(0))
    for i in range(3):
        key, batch = jax.random.key(10 + i), _batch(jax.random.key(20 + i))
        expected = jax.jit(_clac_update_by_hand)(key, state, batch)
        state, _ = jax.jit(agent.update)(key, state, batch)
        chex.assert_trees_all_equal(state, expected)


def test_spec_must_match_the_state_fields():
    spec = ActorCriticSpec(
        state_type=LACState,
        critic_loss=lac_critic_loss,
        actor_loss=functools.partial(losses.lac_actor_loss, alpha3=1.0),
        target_actor=False,  # LACState keeps a target policy
    )
    with pytest.raises(ValueError, match="target_actor_params"):
        make_actor_critic(LACConfig(), spec, OBS, ACT)
