"""Policy and critic networks (flax.linen) and the squashed Gaussian policy maths.

Three modules, all float32 whatever the global precision, Xavier (Glorot) uniform
weights and zero biases (paper appendix):

* :class:`SquashedGaussianActor`: MLP -> (mean, log_std) of a diagonal Gaussian over the
  pre-squash action u; the action is a = tanh(u) in [-1, 1]^A (Haarnoja et al. 2018,
  appendix C).
* :class:`LyapunovCritic`: L_c(s, a) = ||h(s, a)||^2 with h the last hidden layer, so
  L_c >= 0 by construction (Han et al. 2020; paper appendix).
* :class:`TwinQCritic`: an ensemble of Q(s, a) MLPs for SAC, output ``[C, ...]``.

:class:`Networks` bundles the three modules so that losses receive them as one explicit
argument.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxcal.agents.configs import SACConfig, _ActorCriticConfig
from jaxcal.typedefs import Array, PRNGKey

_KERNEL_INIT = nn.initializers.xavier_uniform()
_LOG_2 = math.log(2.0)


class MLP(nn.Module):
    """Dense layers with leaky-ReLU activations.

    Attributes:
        hidden_sizes: widths of the hidden layers.
        negative_slope: slope of the leaky ReLU for negative inputs.
    """

    hidden_sizes: Sequence[int]
    negative_slope: float = 0.2

    @nn.compact
    def __call__(self, x: Array) -> Array:
        x = x.astype(jnp.float32)
        for size in self.hidden_sizes:
            x = nn.Dense(size, kernel_init=_KERNEL_INIT, param_dtype=jnp.float32)(x)
            x = nn.leaky_relu(x, negative_slope=self.negative_slope)
        return x


class SquashedGaussianActor(nn.Module):
    """Gaussian policy head over the pre-tanh action.

    Attributes:
        hidden_sizes: hidden widths of the torso.
        action_size: A.
        negative_slope: leaky-ReLU slope.
        log_std_min, log_std_max: clip of the log standard deviation.
        prior: ``(start, gain)``: the mean is a correction of the action
            ``gain * obs[start : start + A]`` (``_ActorCriticConfig.actor_prior``);
            ``None``: none. It adds no parameter.
    """

    hidden_sizes: Sequence[int]
    action_size: int
    negative_slope: float = 0.2
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    prior: tuple[int, float] | None = None

    @nn.compact
    def __call__(self, obs: Array) -> tuple[Array, Array]:
        """Maps ``obs [..., O]`` to ``(mean [..., A], log_std [..., A])``."""
        h = MLP(self.hidden_sizes, self.negative_slope)(obs)
        # with a prior the untrained mean is the prior's alone (a zero head)
        head_init = _KERNEL_INIT if self.prior is None else nn.initializers.zeros
        mean = nn.Dense(self.action_size, kernel_init=head_init)(h)
        log_std = nn.Dense(self.action_size, kernel_init=_KERNEL_INIT)(h)
        if self.prior is not None:
            start, gain = self.prior
            base = gain * obs[..., start : start + self.action_size]
            # 0.999: the prior's pre-tanh action stays finite (|u| < 3.8)
            mean = mean + jnp.arctanh(jnp.clip(base, -0.999, 0.999)).astype(mean.dtype)
        return mean, jnp.clip(log_std, self.log_std_min, self.log_std_max)


class LyapunovCritic(nn.Module):
    """Lyapunov critic L_c(s, a) = sum_j h_j(s, a)^2 over the last hidden layer."""

    hidden_sizes: Sequence[int]
    negative_slope: float = 0.2

    @nn.compact
    def __call__(self, obs: Array, action: Array) -> Array:
        """Maps ``obs [..., O]``, ``action [..., A]`` to ``L [...]`` (non-negative)."""
        x = jnp.concatenate([obs.astype(jnp.float32), action.astype(jnp.float32)], -1)
        h = MLP(self.hidden_sizes, self.negative_slope)(x)
        return jnp.sum(jnp.square(h), axis=-1)


class QCritic(nn.Module):
    """One Q(s, a) MLP with a linear scalar output."""

    hidden_sizes: Sequence[int]
    negative_slope: float = 0.2

    @nn.compact
    def __call__(self, obs: Array, action: Array) -> Array:
        x = jnp.concatenate([obs.astype(jnp.float32), action.astype(jnp.float32)], -1)
        h = MLP(self.hidden_sizes, self.negative_slope)(x)
        return nn.Dense(1, kernel_init=_KERNEL_INIT)(h)[..., 0]


class TwinQCritic(nn.Module):
    """``num_critics`` independent Q critics evaluated together: output ``[C, ...]``."""

    hidden_sizes: Sequence[int]
    negative_slope: float = 0.2
    num_critics: int = 2

    @nn.compact
    def __call__(self, obs: Array, action: Array) -> Array:
        ensemble = nn.vmap(
            QCritic,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            out_axes=0,
            axis_size=self.num_critics,
        )
        return ensemble(self.hidden_sizes, self.negative_slope)(obs, action)


class Networks(NamedTuple):
    """The modules of one agent (static: closed over, never traced).

    ``critic`` is a :class:`LyapunovCritic` (LAC/CLAC) or a :class:`TwinQCritic` (SAC).
    """

    actor: SquashedGaussianActor
    critic: nn.Module


def make_networks(cfg: _ActorCriticConfig, action_size: int) -> Networks:
    """Builds the actor and the critic an agent config asks for (Q twins for SAC)."""
    actor = SquashedGaussianActor(
        hidden_sizes=cfg.actor_hidden_sizes,
        action_size=action_size,
        negative_slope=cfg.leaky_relu_slope,
        log_std_min=cfg.log_std_min,
        log_std_max=cfg.log_std_max,
        prior=getattr(cfg, "actor_prior", None),
    )
    if isinstance(cfg, SACConfig):
        critic = TwinQCritic(
            cfg.critic_hidden_sizes, cfg.leaky_relu_slope, cfg.num_critics
        )
    else:
        critic = LyapunovCritic(cfg.critic_hidden_sizes, cfg.leaky_relu_slope)
    return Networks(actor=actor, critic=critic)


def squashed_log_prob(pre_tanh: Array, mean: Array, log_std: Array) -> Array:
    """log pi(a|s) of a = tanh(u), u ~ N(mean, exp(log_std)^2) (Haarnoja 2018, eq. 21).

    Uses log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), which stays finite where
    tanh(u) rounds to +-1.

    Args:
        pre_tanh: u, ``[..., A]``.
        mean, log_std: Gaussian parameters, ``[..., A]``.

    Returns:
        ``[...]`` log-density of the squashed action (summed over A).
    """
    z = (pre_tanh - mean) * jnp.exp(-log_std)
    gaussian = -0.5 * jnp.square(z) - log_std - 0.5 * math.log(2.0 * math.pi)
    log_det = 2.0 * (_LOG_2 - pre_tanh - jax.nn.softplus(-2.0 * pre_tanh))
    return jnp.sum(gaussian - log_det, axis=-1)


def sample_squashed_gaussian(
    key: PRNGKey, mean: Array, log_std: Array
) -> tuple[Array, Array]:
    """Reparameterised sample a = tanh(mean + std * eps) and its log-probability.

    Args:
        key: PRNG key for eps ~ N(0, I).
        mean, log_std: ``[..., A]``.

    Returns:
        ``(action [..., A], log_prob [...])``.
    """
    eps = jax.random.normal(key, mean.shape, dtype=mean.dtype)
    pre_tanh = mean + jnp.exp(log_std) * eps
    return jnp.tanh(pre_tanh), squashed_log_prob(pre_tanh, mean, log_std)


def deterministic_action(mean: Array) -> Array:
    """pi*(s) = tanh(mean), the squashed mean: deployment action (paper eq. CLAC)."""
    return jnp.tanh(mean)
