"""The actor-critic update that SAC, LAC and CLAC share, written once.

The three agents run the same step on a minibatch (paper Algorithm 1): a critic step,
a policy step against the updated critic, one step per multiplier, and the Polyak
update of the targets. They differ only in parts, which an agent module collects in
an :class:`ActorCriticSpec`:

* the critic loss (SAC's soft Q regression or the Lyapunov critic's J(L_c));
* the actor loss (SAC's, eq. LAC or eq. CLAC);
* the multipliers besides the entropy temperature, which every agent learns
  (LAC's Lyapunov multiplier, CLAC's smoothness multiplier as well);
* whether a Polyak-averaged policy is kept (LAC/CLAC sample a' from it).

:func:`make_actor_critic` turns a spec into an :class:`~jaxcal.agents.common.Agent`.
A multiplier is learnt as its logarithm with Adam, is read as ``exp`` (its *weight*)
before any step of the update, and its weight reaches both losses as the keyword
argument of its name, so the losses of :mod:`jaxcal.agents.losses` plug in directly.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from jaxcal.agents import losses
from jaxcal.agents.buffer import Transition
from jaxcal.agents.common import (
    Agent,
    check_sizes,
    clip_log_multiplier,
    copy_tree,
    init_log_multiplier,
    init_optimized,
    make_act,
    minimize,
    polyak_update,
)
from jaxcal.agents.configs import _ActorCriticConfig
from jaxcal.agents.networks import Networks, make_networks
from jaxcal.typedefs import Array, Metrics, PRNGKey

# ``critic_loss(critic_params, state, batch, key, networks, *, gamma, **weights)
# -> (loss, aux)``: the state gives the targets, and which policy samples a'.
CriticLoss = Callable[..., tuple[Array, Metrics]]
# ``actor_loss(actor_params, critic_params, batch, key, networks, **weights)
# -> (loss, aux)``, with ``aux`` holding what the multiplier losses read.
ActorLoss = Callable[..., tuple[Array, Metrics]]


@dataclasses.dataclass(frozen=True)
class Multiplier:
    """A positive multiplier learnt in log space.

    Attributes:
        name: the keyword its weight is passed to the losses under; the agent state
            keeps its log and Adam state in the field ``log_<name>``.
        signal: the entry of the actor loss's aux that drives it (e.g.
            ``"lyapunov_decrease"``).
        loss: ``loss(log_value, actor_aux[signal]) -> (loss, aux)``, differentiated
            in the log value (a loss of :mod:`jaxcal.agents.losses`).
        initial_value: its value before the first update (> 0).
        learning_rate: Adam learning rate of its logarithm.
        max_value: projection bound after each step (:func:`clip_log_multiplier`);
            None leaves the multiplier unbounded.
    """

    name: str
    signal: str
    loss: Callable[[Array, Array], tuple[Array, Metrics]]
    initial_value: float
    learning_rate: float
    max_value: float | None = None

    @property
    def field(self) -> str:
        """Name of the agent-state field holding the log value."""
        return f"log_{self.name}"


@dataclasses.dataclass(frozen=True)
class ActorCriticSpec:
    """The parts in which one actor-critic algorithm differs from another.

    Attributes:
        state_type: the agent's ``flax.struct`` state class. Its fields are ``actor``,
            ``critic``, ``target_critic_params``, ``step``, ``target_actor_params`` if
            ``target_actor``, and ``log_<name>`` per multiplier (the temperature too).
        critic_loss: see :data:`CriticLoss`.
        actor_loss: see :data:`ActorLoss`.
        multipliers: learnt after the entropy temperature, in this order.
        target_actor: keep a Polyak-averaged copy of the policy.
    """

    state_type: type
    critic_loss: CriticLoss
    actor_loss: ActorLoss
    multipliers: tuple[Multiplier, ...] = ()
    target_actor: bool = False


def entropy_temperature(cfg: _ActorCriticConfig, action_size: int) -> Multiplier:
    """The entropy temperature (paper beta), driven towards the target entropy."""
    return Multiplier(
        name="entropy_temperature",
        signal="log_prob",
        loss=functools.partial(
            losses.entropy_temperature_loss,
            target_entropy=cfg.resolved_target_entropy(action_size),
        ),
        initial_value=cfg.initial_entropy_temperature,
        learning_rate=cfg.entropy_temperature_lr,
    )


def _state_fields(
    spec: ActorCriticSpec, multipliers: tuple[Multiplier, ...]
) -> set[str]:
    targets = {"target_actor_params"} if spec.target_actor else set()
    logs = {m.field for m in multipliers}
    return {"actor", "critic", "target_critic_params", "step"} | targets | logs


def _check_state_type(spec: ActorCriticSpec, multipliers: tuple[Multiplier, ...]):
    """``spec.state_type`` must hold exactly the fields the spec implies."""
    fields = {f.name for f in dataclasses.fields(spec.state_type)}
    if fields != _state_fields(spec, multipliers):
        raise ValueError(
            f"{spec.state_type.__name__} has fields {sorted(fields)}, the spec needs "
            f"{sorted(_state_fields(spec, multipliers))}"
        )


class _Learners(NamedTuple):
    """The networks and one Adam per learnt quantity (static: closed over by the
    agent's ``init`` and ``update``, never traced)."""

    networks: Networks
    actor_optimizer: optax.GradientTransformation
    critic_optimizer: optax.GradientTransformation
    multipliers: tuple[Multiplier, ...]  # the entropy temperature first
    multiplier_optimizers: tuple[optax.GradientTransformation, ...]


def _init_state(
    key: PRNGKey,
    spec: ActorCriticSpec,
    learners: _Learners,
    observation_size: int,
    action_size: int,
) -> Any:
    """A fresh agent state: networks initialised, targets copied, each multiplier at
    its initial value."""
    key_actor, key_critic = jax.random.split(key)
    obs = jnp.zeros((1, observation_size), jnp.float32)
    action = jnp.zeros((1, action_size), jnp.float32)
    actor_params = learners.networks.actor.init(key_actor, obs)
    critic_params = learners.networks.critic.init(key_critic, obs, action)
    logs = {
        m.field: init_log_multiplier(optimizer, m.initial_value)
        for m, optimizer in zip(
            learners.multipliers, learners.multiplier_optimizers, strict=True
        )
    }
    if spec.target_actor:
        logs["target_actor_params"] = copy_tree(actor_params)
    return spec.state_type(
        actor=init_optimized(learners.actor_optimizer, actor_params),
        critic=init_optimized(learners.critic_optimizer, critic_params),
        target_critic_params=copy_tree(critic_params),
        step=jnp.zeros((), jnp.int32),
        **logs,
    )


def _step_multipliers(
    learners: _Learners, state: Any, actor_aux: Metrics
) -> tuple[dict, Metrics]:
    """One step per multiplier on its loss of the actor aux, each log value projected
    when bounded: (new log values by state field, the losses' aux)."""
    changes, metrics = {}, {}
    for m, optimizer in zip(
        learners.multipliers, learners.multiplier_optimizers, strict=True
    ):
        log_value, aux = minimize(
            optimizer, getattr(state, m.field), m.loss, actor_aux[m.signal]
        )
        if m.max_value is not None:
            log_value = clip_log_multiplier(log_value, m.max_value)
        changes[m.field] = log_value
        metrics.update(aux)
    return changes, metrics


def _update(
    key: PRNGKey,
    state: Any,
    batch: Transition,
    cfg: _ActorCriticConfig,
    spec: ActorCriticSpec,
    learners: _Learners,
) -> tuple[Any, Metrics]:
    """One update on a minibatch, in the order of :func:`make_actor_critic`."""
    key_critic, key_actor = jax.random.split(key)
    # Both losses weigh with the multipliers as they were before this update.
    weights = {
        m.name: jnp.exp(getattr(state, m.field).params) for m in learners.multipliers
    }
    critic, critic_aux = minimize(
        learners.critic_optimizer,
        state.critic,
        spec.critic_loss,
        state,
        batch,
        key_critic,
        learners.networks,
        gamma=cfg.gamma,
        **weights,
    )
    actor, actor_aux = minimize(
        learners.actor_optimizer,
        state.actor,
        spec.actor_loss,
        critic.params,
        batch,
        key_actor,
        learners.networks,
        **weights,
    )
    changes, multiplier_aux = _step_multipliers(learners, state, actor_aux)
    metrics = {**critic_aux, **actor_aux}
    metrics.update(multiplier_aux)
    if spec.target_actor:
        changes["target_actor_params"] = polyak_update(
            state.target_actor_params, actor.params, cfg.tau
        )
    new_state = state.replace(
        actor=actor,
        critic=critic,
        target_critic_params=polyak_update(
            state.target_critic_params, critic.params, cfg.tau
        ),
        step=state.step + 1,
        **changes,
    )
    return new_state, metrics


def make_actor_critic(
    cfg: _ActorCriticConfig,
    spec: ActorCriticSpec,
    observation_size: int,
    action_size: int,
) -> Agent:
    """Builds an agent from the shared hyperparameters and its differing parts.

    The agent's ``update(key, state, batch)`` does, on one minibatch (Algorithm 1):

    1. a critic step on ``spec.critic_loss``;
    2. a policy step on ``spec.actor_loss`` against the updated critic;
    3. a step per multiplier (the entropy temperature first, then
       ``spec.multipliers``) on its loss of the actor aux, each log value projected
       onto (0, ``max_value``] if bounded;
    4. the Polyak update (``cfg.tau``) of the target critic and, with
       ``spec.target_actor``, of the target policy.

    Its metrics are the critic's, the actor's and the multipliers' aux entries.

    Args:
        cfg: hyperparameters (networks, learning rates, gamma, tau, temperature).
        spec: the algorithm's parts.
        observation_size: O.
        action_size: A.

    Returns:
        ``Agent(init, act, update, observation_size, action_size)``.

    Raises:
        ValueError: a size is not a positive int, or ``spec.state_type``'s fields
            are not those the spec implies.
    """
    check_sizes(observation_size, action_size)
    multipliers = (entropy_temperature(cfg, action_size), *spec.multipliers)
    _check_state_type(spec, multipliers)
    learners = _Learners(
        networks=make_networks(cfg, action_size),
        actor_optimizer=optax.adam(cfg.actor_lr),
        critic_optimizer=optax.adam(cfg.critic_lr),
        multipliers=multipliers,
        multiplier_optimizers=tuple(optax.adam(m.learning_rate) for m in multipliers),
    )

    def init(key: PRNGKey) -> Any:
        return _init_state(key, spec, learners, observation_size, action_size)

    def update(key: PRNGKey, state: Any, batch: Transition) -> tuple[Any, Metrics]:
        return _update(key, state, batch, cfg, spec, learners)

    actor = learners.networks.actor
    return Agent(init, make_act(actor), update, observation_size, action_size)
