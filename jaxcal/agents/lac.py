"""Lyapunov actor-critic (Han et al. 2020), the paper's LAC ablation.

:func:`make_lac` returns an :class:`~jaxcal.agents.common.Agent` built by
:func:`~jaxcal.agents.actor_critic.make_actor_critic`, whose ``update`` does, on one
minibatch (paper Algorithm 1 without the CLAC term):

1. a Lyapunov critic step on J(L_c) with the target critic and target policy;
2. a policy step on eq. LAC against the updated critic;
3. a step on log(entropy temperature) (paper eq. temperature update) and on
   log(Lyapunov multiplier) (paper eq. gamma update), the latter projected onto
   (0, ``max_lyapunov_multiplier``];
4. the Polyak update of the target critic and target policy (tau).

The Lyapunov critic loss and multiplier defined here are CLAC's too.
"""

from __future__ import annotations

import functools

from flax import struct

from jaxcal.agents import losses
from jaxcal.agents.actor_critic import ActorCriticSpec, Multiplier, make_actor_critic
from jaxcal.agents.buffer import Transition
from jaxcal.agents.common import Agent, Optimized
from jaxcal.agents.configs import LACConfig
from jaxcal.agents.networks import Networks
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


def lac_critic_loss(
    critic_params: PyTree,
    state: LACState,
    batch: Transition,
    key: PRNGKey,
    networks: Networks,
    *,
    gamma: float,
    **weights: Array,
) -> tuple[Array, Metrics]:
    """:func:`~jaxcal.agents.losses.lyapunov_critic_loss` with the target critic and
    target policy of ``state`` (a LAC or CLAC state).

    Returns:
        ``(loss, {"critic_loss", "lyapunov_value", "lyapunov_target"})``.
    """
    del weights  # J(L_c) is weighted by no multiplier
    return losses.lyapunov_critic_loss(
        critic_params,
        state.target_critic_params,
        state.target_actor_params,
        batch,
        key,
        networks,
        gamma=gamma,
    )


def lyapunov_multiplier(cfg: LACConfig) -> Multiplier:
    """The Lyapunov multiplier (paper lambda), driven by the decrease Delta."""
    return Multiplier(
        name="lyapunov_multiplier",
        signal="lyapunov_decrease",
        loss=losses.lyapunov_multiplier_loss,
        initial_value=cfg.initial_lyapunov_multiplier,
        learning_rate=cfg.lyapunov_multiplier_lr,
        max_value=cfg.max_lyapunov_multiplier,
    )


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
    spec = ActorCriticSpec(
        state_type=LACState,
        critic_loss=lac_critic_loss,
        actor_loss=functools.partial(losses.lac_actor_loss, alpha3=cfg.alpha3),
        multipliers=(lyapunov_multiplier(cfg),),
        target_actor=True,
    )
    return make_actor_critic(cfg, spec, observation_size, action_size)
