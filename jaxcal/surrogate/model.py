"""The learned simulator D of the tracking MDP: x̂_{t+1} = D(w_{t+1}, x̂_t, θ_{t+1}).

Tian et al. (§3.1, eq. "discrete_system"; appendix "Simulator Network") replace the
physics F by an MLP with three hidden layers of 100 ReLU units and a linear output of
the sensor dimension n, so that RL training steps are cheap. Its inputs are the next
operating condition, the current model output and the next calibration parameters,
concatenated in that order and standardised with training statistics; its output is the
next model output in sensor units. The N-CMAPSS-like engine model is quasi-steady, so
the network predicts x̂_{t+1} directly rather than an increment (as in the paper).

:func:`surrogate_apply` has exactly the ``dynamics(dyn_params, w_next, xhat, theta)``
signature of the tracking environment, with :class:`SurrogateParams` as ``dyn_params``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from jaxcal.nets.mlp import MLP, Normalizer, RegressorConfig, RegressorParams
from jaxcal.nets.mlp import regressor_apply as _regressor_apply
from jaxcal.typedefs import Array, PRNGKey


@dataclasses.dataclass(frozen=True)
class SurrogateConfig:
    """Architecture and fitting settings of the surrogate D (paper appendix)."""

    hidden_sizes: tuple[int, ...] = (100, 100, 100)  # paper: n1 = n2 = n3 = 100
    activation: str = "relu"  # paper: ReLU hidden layers, identity output
    # Adam on minibatches of 256; the paper gives no surrogate learning rate.
    fit: RegressorConfig = RegressorConfig(
        learning_rate=1e-3,
        batch_size=256,
        num_epochs=100,
        validation_fraction=0.1,
        patience=10,
    )


@struct.dataclass
class SurrogateParams:
    """Trained surrogate: weights and statistics (leaves) plus its static shape.

    The static fields let :func:`surrogate_apply` rebuild the network without a module
    argument and check input sizes at trace time; they are not checkpoint leaves, so a
    restore target comes from ``jax.eval_shape`` of :func:`init_surrogate_params`.
    """

    regressor: RegressorParams
    hidden_sizes: tuple[int, ...] = struct.field(pytree_node=False)
    activation: str = struct.field(pytree_node=False)
    condition_dim: int = struct.field(pytree_node=False)  # W
    sensor_dim: int = struct.field(pytree_node=False)  # S
    theta_dim: int = struct.field(pytree_node=False)  # P


def make_surrogate_network(
    hidden_sizes: tuple[int, ...], sensor_dim: int, activation: str = "relu"
) -> MLP:
    """The MLP of D: ``[..., W + S + P] -> [..., S]``."""
    return MLP(
        hidden_sizes=tuple(hidden_sizes), output_dim=sensor_dim, activation=activation
    )


def init_surrogate_params(
    key: PRNGKey,
    condition_dim: int,
    sensor_dim: int,
    theta_dim: int,
    cfg: SurrogateConfig,
) -> SurrogateParams:
    """A fresh surrogate with identity normalisation (also serves as restore target).

    Args:
        key: PRNG key for the Glorot initialisation.
        condition_dim: W, size of w.
        sensor_dim: S, size of x.
        theta_dim: P, size of θ.
        cfg: architecture.
    """
    in_dim = condition_dim + sensor_dim + theta_dim
    net = make_surrogate_network(cfg.hidden_sizes, sensor_dim, cfg.activation)
    weights = jax.jit(net.init)(key, jnp.zeros((1, in_dim), jnp.float32))["params"]

    def identity(d):
        return Normalizer(mean=jnp.zeros(d, jnp.float32), std=jnp.ones(d, jnp.float32))

    return SurrogateParams(
        regressor=RegressorParams(
            net=weights, input_norm=identity(in_dim), target_norm=identity(sensor_dim)
        ),
        hidden_sizes=tuple(cfg.hidden_sizes),
        activation=cfg.activation,
        condition_dim=condition_dim,
        sensor_dim=sensor_dim,
        theta_dim=theta_dim,
    )


def surrogate_apply(
    params: SurrogateParams, w_next: Array, xhat: Array, theta: Array
) -> Array:
    """One step of D: x̂_{t+1} = D(w_{t+1}, x̂_t, θ_{t+1}).

    Tian et al., §3.1, eq. "discrete_system".

    Leading (batch) dimensions broadcast against each other, so a single θ ``[P]`` can
    drive a batch of states. The network runs in float32; the result takes the dtype of
    ``xhat`` so that ``lax.scan`` carries keep their type.

    Args:
        params: trained (or initial) surrogate.
        w_next: ``[..., W]`` operating condition at t + 1.
        xhat: ``[..., S]`` model output at t.
        theta: ``[..., P]`` calibration parameters at t + 1.

    Returns:
        ``[..., S]`` model output at t + 1, in sensor units.
    """
    expected = {
        "w_next": params.condition_dim,
        "xhat": params.sensor_dim,
        "theta": params.theta_dim,
    }
    given = {"w_next": w_next, "xhat": xhat, "theta": theta}
    for name, size in expected.items():
        if jnp.ndim(given[name]) < 1 or jnp.shape(given[name])[-1] != size:
            raise ValueError(
                f"surrogate_apply: {name} must have last dimension {size}, "
                f"got shape {jnp.shape(given[name])}"
            )
    lead = jnp.broadcast_shapes(*(jnp.shape(v)[:-1] for v in given.values()))
    inputs = jnp.concatenate(
        [
            jnp.broadcast_to(v, lead + v.shape[-1:]).astype(jnp.float32)
            for v in given.values()
        ],
        axis=-1,
    )
    net = make_surrogate_network(
        params.hidden_sizes, params.sensor_dim, params.activation
    )
    out = _regressor_apply(net, params.regressor, inputs)
    out_dtype = xhat.dtype if jnp.issubdtype(xhat.dtype, jnp.floating) else out.dtype
    return out.astype(out_dtype)


def surrogate_rollout(
    params: SurrogateParams, w: Array, x0: Array, theta: Array
) -> Array:
    """Free-running (closed-loop) prediction of one trajectory with ``lax.scan``.

    Args:
        params: surrogate.
        w: ``[T, W]`` operating conditions.
        x0: ``[S]`` initial model output (usually the measured x_0).
        theta: ``[T, P]`` calibration parameters.

    Returns:
        ``[T, S]``: x̂_0 = x0 and x̂_{t+1} = D(w_{t+1}, x̂_t, θ_{t+1}).
    """

    def step(xhat, inputs):
        w_next, theta_next = inputs
        xhat_next = surrogate_apply(params, w_next, xhat, theta_next)
        return xhat_next, xhat_next

    _, xhat = jax.lax.scan(step, x0, (w[1:], theta[1:]))
    return jnp.concatenate([x0[None], xhat], axis=0)
