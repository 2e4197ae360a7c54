"""Losses of SAC, LAC and CLAC as pure module-level functions.

Conventions: the differentiated argument comes first, every other input is explicit
(networks, batch, key, scalar weights), and each function returns ``(loss, aux)`` with
``aux`` a dict of scalar diagnostics. Targets and the multipliers used as weights are
wrapped in ``lax.stop_gradient`` here, visibly, not by the callers.

The environment gives a *cost* c >= 0 that the agents minimise, so the SAC objective is
E[sum_t gamma^t (c_t + beta log pi(a_t|s_t))], the mirror image of Haarnoja et al.'s
reward maximisation: entropy enters with a + sign and the twin critics are combined with
a max (pessimistic for costs) instead of a min.

Equations cite Tian et al., "Real-Time Model Calibration with Deep Reinforcement
Learning" ("paper"): J(L_c), eq. LAC (actor), eq. temperature update (beta), eq. gamma
update (lambda, named "gamma update" in the paper's labels) and eq. CLAC.
Multipliers are named by role (see :mod:`jaxcal.agents.configs`):
entropy_temperature = paper beta, lyapunov_multiplier = paper lambda,
smoothness_multiplier = paper alpha.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcal.agents.buffer import Transition
from jaxcal.agents.networks import (
    Networks,
    deterministic_action,
    sample_squashed_gaussian,
)
from jaxcal.typedefs import Array, Metrics, PRNGKey, PyTree

_NORM_EPS = 1e-12  # keeps d||x||/dx finite at x = 0


def _sample_action(
    networks: Networks, actor_params: PyTree, obs: Array, key: PRNGKey
) -> tuple[Array, Array]:
    mean, log_std = networks.actor.apply(actor_params, obs)
    return sample_squashed_gaussian(key, mean, log_std)


# --------------------------------------------------------------------------- SAC


def soft_q_critic_loss(
    critic_params: PyTree,
    target_critic_params: PyTree,
    actor_params: PyTree,
    batch: Transition,
    key: PRNGKey,
    networks: Networks,
    *,
    gamma: float,
    entropy_temperature: Array,
) -> tuple[Array, Metrics]:
    """Twin-Q soft Bellman loss on costs (Haarnoja et al. 2018, eq. 5-6, cost form).

    y = c + gamma (1 - terminal) [max_i Qbar_i(s', a') + beta log pi(a'|s')],
    a' ~ pi(.|s'); loss = 1/2 sum_i mean_B (Q_i(s, a) - y)^2.

    Args:
        critic_params: parameters of the :class:`TwinQCritic` (differentiated).
        target_critic_params: Polyak-averaged critic parameters.
        actor_params: current policy parameters (for a').
        batch: transitions, leading axis ``[B]``.
        key: PRNG key for a'.
        networks: the agent's modules.
        gamma: discount factor.
        entropy_temperature: beta > 0, scalar.

    Returns:
        ``(loss, {"critic_loss", "q_value", "q_target"})``.
    """
    next_action, next_log_prob = _sample_action(
        networks, actor_params, batch.next_obs, key
    )
    next_q = networks.critic.apply(target_critic_params, batch.next_obs, next_action)
    soft_next = jnp.max(next_q, axis=0) + entropy_temperature * next_log_prob
    target = batch.cost + gamma * (1.0 - batch.terminal) * soft_next
    target = jax.lax.stop_gradient(target)
    q = networks.critic.apply(critic_params, batch.obs, batch.action)  # [C, B]
    loss = 0.5 * jnp.sum(jnp.mean(jnp.square(q - target[None]), axis=-1))
    return loss, {"critic_loss": loss, "q_value": q.mean(), "q_target": target.mean()}


def sac_actor_loss(
    actor_params: PyTree,
    critic_params: PyTree,
    batch: Transition,
    key: PRNGKey,
    networks: Networks,
    *,
    entropy_temperature: Array,
) -> tuple[Array, Metrics]:
    """SAC policy loss on costs: mean_B [beta log pi(a~|s) + max_i Q_i(s, a~)].

    a~ ~ pi(.|s) (Haarnoja et al. 2018, eq. 7 with the cost sign).

    Returns:
        ``(loss, {"actor_loss", "log_prob", "entropy"})``.
    """
    action, log_prob = _sample_action(networks, actor_params, batch.obs, key)
    q = jnp.max(networks.critic.apply(critic_params, batch.obs, action), axis=0)
    beta = jax.lax.stop_gradient(entropy_temperature)
    loss = jnp.mean(beta * log_prob + q)
    mean_log_prob = jax.lax.stop_gradient(log_prob.mean())
    return loss, {
        "actor_loss": loss,
        "log_prob": mean_log_prob,
        "entropy": -mean_log_prob,
    }


def entropy_temperature_loss(
    log_temperature: Array, log_prob: Array, target_entropy: float
) -> tuple[Array, Metrics]:
    """Temperature loss -log(beta) (E[log pi] + H_t) (paper eq. temperature update).

    Minimising it raises beta while the entropy -E[log pi] is below the target H_t.
    The reference implementation multiplies by log(beta) instead of beta; the sign of
    the gradient is the same and the step is scale-free in log space.

    Args:
        log_temperature: log beta, scalar (differentiated).
        log_prob: mean log pi(a|s) over the batch, scalar.
        target_entropy: H_t (paper: -d).

    Returns:
        ``(loss, {"entropy_temperature"})``.
    """
    gap = jax.lax.stop_gradient(log_prob + target_entropy)
    loss = -log_temperature * gap
    return loss, {"entropy_temperature": jnp.exp(log_temperature)}


# --------------------------------------------------------------------- LAC / CLAC


def lyapunov_critic_loss(
    critic_params: PyTree,
    target_critic_params: PyTree,
    target_actor_params: PyTree,
    batch: Transition,
    key: PRNGKey,
    networks: Networks,
    *,
    gamma: float,
) -> tuple[Array, Metrics]:
    """Lyapunov critic regression J(L_c) (paper, equations before eq. LAC).

    L_target = c + gamma (1 - terminal) Lbar(s', a'), a' ~ pibar(.|s') with the
    Polyak-averaged critic and policy of Algorithm 1; loss = 1/2 mean_B (L_c(s,a) -
    L_target)^2.

    Args:
        critic_params: :class:`LyapunovCritic` parameters (differentiated).
        target_critic_params, target_actor_params: Polyak-averaged parameters.
        batch: transitions ``[B]``.
        key: PRNG key for a'.
        networks: the agent's modules.
        gamma: discount factor.

    Returns:
        ``(loss, {"critic_loss", "lyapunov_value", "lyapunov_target"})``.
    """
    next_action, _ = _sample_action(networks, target_actor_params, batch.next_obs, key)
    next_value = networks.critic.apply(
        target_critic_params, batch.next_obs, next_action
    )
    target = batch.cost + gamma * (1.0 - batch.terminal) * next_value
    target = jax.lax.stop_gradient(target)
    value = networks.critic.apply(critic_params, batch.obs, batch.action)
    loss = 0.5 * jnp.mean(jnp.square(value - target))
    return loss, {
        "critic_loss": loss,
        "lyapunov_value": value.mean(),
        "lyapunov_target": target.mean(),
    }


def _lyapunov_actor_terms(
    actor_params: PyTree,
    critic_params: PyTree,
    batch: Transition,
    key: PRNGKey,
    networks: Networks,
    alpha3: float,
) -> tuple[Array, Array, Array]:
    """Shared part of eq. LAC / eq. CLAC: log pi(a~|s), Delta and pi*(s) - pi*(s').

    The policy runs once on ``[s; s']`` and the critic once on ``[(s', a''); (s, a)]``:
    one pass of 2B rows instead of two of B (the update's cost is these matmuls).
    """
    num = batch.obs.shape[0]
    key_now, key_next = jax.random.split(key)
    mean, log_std = networks.actor.apply(
        actor_params, jnp.concatenate([batch.obs, batch.next_obs])
    )
    _, log_prob = sample_squashed_gaussian(key_now, mean[:num], log_std[:num])
    next_action, _ = sample_squashed_gaussian(key_next, mean[num:], log_std[num:])
    values = networks.critic.apply(
        critic_params,
        jnp.concatenate([batch.next_obs, batch.obs]),
        jnp.concatenate([next_action, batch.action.astype(next_action.dtype)]),
    )
    decrease = jnp.mean(values[:num] - values[num:] + alpha3 * batch.cost)
    squashed = deterministic_action(mean)
    return log_prob, decrease, squashed[:num] - squashed[num:]


def _safe_norm(diff: Array) -> Array:
    # The 1e-12 floor keeps d||x||/dx finite where both actions coincide.
    return jnp.sqrt(jnp.sum(jnp.square(diff), axis=-1) + _NORM_EPS)


def lac_actor_loss(
    actor_params: PyTree,
    critic_params: PyTree,
    batch: Transition,
    key: PRNGKey,
    networks: Networks,
    *,
    entropy_temperature: Array,
    lyapunov_multiplier: Array,
    alpha3: float,
) -> tuple[Array, Metrics]:
    """LAC policy loss (paper eq. LAC).

    J(pi) = beta mean_B log pi(a~|s) + lambda Delta,
    Delta = mean_B [L_c(s', a'') - L_c(s, a) + alpha_3 c],
    with a~ ~ pi(.|s), a'' ~ pi(.|s') reparameterised and (s, a, c, s') from the buffer.
    Only L_c(s', a'') and log pi depend on the policy; Delta is also the Lyapunov
    decrease that drives lambda (:func:`lyapunov_multiplier_loss`).

    Args:
        actor_params: policy parameters (differentiated).
        critic_params: current Lyapunov critic parameters (held fixed).
        batch: transitions ``[B]``.
        key: PRNG key, split into ``key_now`` (a~) and ``key_next`` (a'').
        networks: the agent's modules.
        entropy_temperature: beta, scalar.
        lyapunov_multiplier: lambda, scalar.
        alpha3: energy-decrease rate alpha_3.

    Returns:
        ``(loss, {"actor_loss", "log_prob", "entropy", "lyapunov_decrease"})``.
    """
    log_prob, decrease, _ = _lyapunov_actor_terms(
        actor_params, critic_params, batch, key, networks, alpha3
    )
    beta = jax.lax.stop_gradient(entropy_temperature)
    lam = jax.lax.stop_gradient(lyapunov_multiplier)
    loss = beta * jnp.mean(log_prob) + lam * decrease
    mean_log_prob = jax.lax.stop_gradient(log_prob.mean())
    return loss, {
        "actor_loss": loss,
        "log_prob": mean_log_prob,
        "entropy": -mean_log_prob,
        "lyapunov_decrease": jax.lax.stop_gradient(decrease),
    }


def clac_actor_loss(
    actor_params: PyTree,
    critic_params: PyTree,
    batch: Transition,
    key: PRNGKey,
    networks: Networks,
    *,
    entropy_temperature: Array,
    lyapunov_multiplier: Array,
    smoothness_multiplier: Array,
    alpha3: float,
) -> tuple[Array, Metrics]:
    """CLAC policy loss (paper eq. CLAC): eq. LAC + alpha mean_B ||pi*(s) - pi*(s')||.

    s_near is approximated by the next state s' of the same transition (paper: "we use
    the adjacent time space state s_{t+1} ... to approximate s_near"); the distance
    ||pi*(s) - pi*(s')||_2, pi* = tanh(mean), comes from the same policy pass as the
    LAC terms.

    Returns:
        ``(loss, aux)`` with the :func:`lac_actor_loss` entries plus ``"action_change"``
        (mean distance, used by :func:`smoothness_multiplier_loss`).
    """
    log_prob, decrease, diff = _lyapunov_actor_terms(
        actor_params, critic_params, batch, key, networks, alpha3
    )
    change = jnp.mean(_safe_norm(diff))
    beta = jax.lax.stop_gradient(entropy_temperature)
    lam = jax.lax.stop_gradient(lyapunov_multiplier)
    alpha = jax.lax.stop_gradient(smoothness_multiplier)
    loss = beta * jnp.mean(log_prob) + lam * decrease + alpha * change
    mean_log_prob = jax.lax.stop_gradient(log_prob.mean())
    return loss, {
        "actor_loss": loss,
        "log_prob": mean_log_prob,
        "entropy": -mean_log_prob,
        "lyapunov_decrease": jax.lax.stop_gradient(decrease),
        "action_change": jax.lax.stop_gradient(change),
    }


def lyapunov_multiplier_loss(
    log_multiplier: Array, lyapunov_decrease: Array
) -> tuple[Array, Metrics]:
    """Loss -log(lambda) Delta: ascent of lambda Delta (paper eq. gamma update).

    lambda grows while the decrease condition E[L(s') - L(s) + alpha_3 c] <= 0 is
    violated (Delta > 0) and shrinks otherwise; the caller clips lambda to (0, max].

    Args:
        log_multiplier: log lambda, scalar (differentiated).
        lyapunov_decrease: Delta from :func:`lac_actor_loss`, scalar.

    Returns:
        ``(loss, {"lyapunov_multiplier"})``.
    """
    loss = -log_multiplier * jax.lax.stop_gradient(lyapunov_decrease)
    return loss, {"lyapunov_multiplier": jnp.exp(log_multiplier)}


def smoothness_multiplier_loss(
    log_multiplier: Array, mean_action_change: Array, threshold: float
) -> tuple[Array, Metrics]:
    """Loss -log(alpha) (E||pi*(s) - pi*(s_near)|| - threshold) (CLAC reference code).

    The paper gives no update rule for its smoothness multiplier alpha; like the
    reference implementation we raise alpha while the mean action change exceeds the
    threshold and lower it otherwise (a Lagrangian for E||.|| <= threshold).

    Args:
        log_multiplier: log alpha, scalar (differentiated).
        mean_action_change: mean ||pi*(s) - pi*(s_near)||, scalar.
        threshold: target action change.

    Returns:
        ``(loss, {"smoothness_multiplier"})``.
    """
    loss = -log_multiplier * jax.lax.stop_gradient(mean_action_change - threshold)
    return loss, {"smoothness_multiplier": jnp.exp(log_multiplier)}
