"""Soft actor-critic on costs (Haarnoja et al. 2018) with twin Q critics.

The comparison baseline of the paper's learning algorithms: the same policy network and
entropy-temperature adaptation as LAC/CLAC, but a twin soft-Q critic instead of the
Lyapunov critic. :func:`make_sac` returns an :class:`~jaxcal.agents.common.Agent` built
by :func:`~jaxcal.agents.actor_critic.make_actor_critic`; its ``update`` does, on one
minibatch, a critic step, an actor step (against the updated critic), a temperature
step and the Polyak update of the target critics. SAC keeps no target policy: the
soft-Q target samples a' from the online one.
"""

from __future__ import annotations

from flax import struct

from jaxcal.agents import losses
from jaxcal.agents.actor_critic import ActorCriticSpec, make_actor_critic
from jaxcal.agents.buffer import Transition
from jaxcal.agents.common import Agent, Optimized
from jaxcal.agents.configs import SACConfig
from jaxcal.agents.networks import Networks
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


def sac_critic_loss(
    critic_params: PyTree,
    state: SACState,
    batch: Transition,
    key: PRNGKey,
    networks: Networks,
    *,
    gamma: float,
    entropy_temperature: Array,
) -> tuple[Array, Metrics]:
    """:func:`~jaxcal.agents.losses.soft_q_critic_loss` with the target critic and
    the online policy of ``state``.

    Returns:
        ``(loss, {"critic_loss", "q_value", "q_target"})``.
    """
    return losses.soft_q_critic_loss(
        critic_params,
        state.target_critic_params,
        state.actor.params,
        batch,
        key,
        networks,
        gamma=gamma,
        entropy_temperature=entropy_temperature,
    )


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
    spec = ActorCriticSpec(
        state_type=SACState,
        critic_loss=sac_critic_loss,
        actor_loss=losses.sac_actor_loss,
    )
    return make_actor_critic(cfg, spec, observation_size, action_size)
