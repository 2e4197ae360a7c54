"""Constrained Lyapunov actor-critic (CLAC), the paper's proposed learning algorithm.

CLAC is LAC (:mod:`jaxcal.agents.lac`) plus the action-smoothness term of paper
eq. CLAC, alpha E||pi*(s) - pi*(s_near)||, with s_near the next state of the same
transition. :func:`make_clac` returns an :class:`~jaxcal.agents.common.Agent` built by
:func:`~jaxcal.agents.actor_critic.make_actor_critic`, whose ``update`` does, on one
minibatch (paper Algorithm 1):

1. a Lyapunov critic step on J(L_c) with the target critic and target policy;
2. a policy step on eq. CLAC against the updated critic;
3. steps on log(entropy temperature), log(Lyapunov multiplier) (clipped to
   (0, ``max_lyapunov_multiplier``]) and log(smoothness multiplier) (clipped to
   (0, ``max_smoothness_multiplier``]), the latter driving the mean action change
   towards ``smoothness_threshold``;
4. the Polyak update of the target critic and target policy (tau).
"""

from __future__ import annotations

import functools

from flax import struct

from jaxcal.agents import losses
from jaxcal.agents.actor_critic import ActorCriticSpec, Multiplier, make_actor_critic
from jaxcal.agents.common import Agent, Optimized
from jaxcal.agents.configs import CLACConfig
from jaxcal.agents.lac import lac_critic_loss, lyapunov_multiplier
from jaxcal.typedefs import Array, PyTree


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


def smoothness_multiplier(cfg: CLACConfig) -> Multiplier:
    """The smoothness multiplier (paper alpha), driven by the mean action change."""
    return Multiplier(
        name="smoothness_multiplier",
        signal="action_change",
        loss=functools.partial(
            losses.smoothness_multiplier_loss, threshold=cfg.smoothness_threshold
        ),
        initial_value=cfg.initial_smoothness_multiplier,
        learning_rate=cfg.smoothness_multiplier_lr,
        max_value=cfg.max_smoothness_multiplier,
    )


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
    spec = ActorCriticSpec(
        state_type=CLACState,
        critic_loss=lac_critic_loss,
        actor_loss=functools.partial(losses.clac_actor_loss, alpha3=cfg.alpha3),
        multipliers=(lyapunov_multiplier(cfg), smoothness_multiplier(cfg)),
        target_actor=True,
    )
    return make_actor_critic(cfg, spec, observation_size, action_size)
