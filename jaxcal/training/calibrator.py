"""A trained tracking policy as a :class:`~jaxcal.baselines.interface.Calibrator`.

Deployment of the paper's policy (§3.1, "Implementation stage"): with the model output
x-hat_{t-1} carried in the state, each new sample (w_t, x_t) gives

    s = [norm(x-hat_{t-1}), norm(x_t), norm(w_t)],   theta_t = box(pi*(s)),
    x-hat_t = D(w_t, x-hat_{t-1}, theta_t),

with pi* = tanh(mean) the deterministic policy and ``box`` the environment's affine map
to [theta_low, theta_high]. This is the training environment's step shifted by one
index, so on samples t >= 1 the calibrator reproduces
:func:`jaxcal.training.runner.evaluate_policy`. On the first sample there is no x-hat
yet: x-hat = x_0 (as the environment's reset), theta_0 = box(pi*([norm(x_0), norm(x_0),
norm(w_0)])) and x-hat_0 = x_0.

Everything the step reads is a leaf of :class:`PolicyParams`, so one jitted runner
(:func:`make_fleet_runner`) serves any trained policy of the same architecture
without retracing.
"""

from __future__ import annotations

from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from jaxcal.baselines.interface import Calibrator, CalOutput, CalStepOutput, run_fleet
from jaxcal.envs.tracking import Dynamics, EnvParams, action_to_theta
from jaxcal.typedefs import Array, PRNGKey, PyTree


@struct.dataclass
class PolicyParams:
    """Everything a deployed policy reads (all leaves: traced, checkpointable).

    Attributes:
        actor: parameters of the squashed Gaussian actor.
        dyn_params: parameters of the dynamics (surrogate weights or engine constants).
        w_mean, w_std: ``[W]`` training normalisation of w.
        x_mean, x_std: ``[S]`` training normalisation of x and x-hat.
        theta_low, theta_high: ``[P]`` action box.
    """

    actor: PyTree
    dyn_params: PyTree
    w_mean: Array
    w_std: Array
    x_mean: Array
    x_std: Array
    theta_low: Array
    theta_high: Array


@struct.dataclass
class PolicyState:
    """Calibrator state: the model output of the previous sample.

    Attributes:
        xhat: ``[S]`` x-hat_{t-1} (physical units).
        started: ``[]`` bool, False before the first sample.
    """

    xhat: Array
    started: Array


def policy_params_from_env(env_params: EnvParams, actor_params: PyTree) -> PolicyParams:
    """The deployment parameters of a policy trained on ``env_params``."""
    return PolicyParams(
        actor=actor_params,
        dyn_params=env_params.dyn_params,
        w_mean=env_params.w_mean,
        w_std=env_params.w_std,
        x_mean=env_params.x_mean,
        x_std=env_params.x_std,
        theta_low=env_params.theta_low,
        theta_high=env_params.theta_high,
    )


def make_policy_calibrator(
    actor: nn.Module, dynamics: Dynamics, params: PolicyParams
) -> Calibrator:
    """The deterministic policy pi* and the dynamics as ``Calibrator(init, step)``.

    Args:
        actor: the agent's actor module (``apply(params, obs) -> (mean, log_std)``).
        dynamics: ``dynamics(dyn_params, w [W], xhat [S], theta [P]) -> xhat [S]``.
        params: :class:`PolicyParams` (may be traced).

    Returns:
        A :class:`~jaxcal.baselines.interface.Calibrator`; ``aux`` is ``None``.
    """

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> PolicyState:
        del key, w0  # deterministic; x-hat starts at the first measurement
        return PolicyState(xhat=x0, started=jnp.zeros((), bool))

    def step(
        state: PolicyState, w_t: Array, x_t: Array
    ) -> tuple[PolicyState, CalStepOutput]:
        xhat_prev = jnp.where(state.started, state.xhat, x_t)
        obs = jnp.concatenate(
            [
                (xhat_prev - params.x_mean) / params.x_std,
                (x_t - params.x_mean) / params.x_std,
                (w_t - params.w_mean) / params.w_std,
            ]
        ).astype(jnp.float32)
        mean, _ = actor.apply(params.actor, obs)
        theta = action_to_theta(jnp.tanh(mean), params)
        xhat = dynamics(params.dyn_params, w_t, xhat_prev, theta).astype(x_t.dtype)
        xhat = jnp.where(state.started, xhat, x_t)
        new_state = PolicyState(xhat=xhat, started=jnp.ones((), bool))
        return new_state, CalStepOutput(theta=theta, xhat=xhat)

    return Calibrator(init, step)


def make_fleet_runner(
    actor: nn.Module, dynamics: Dynamics, *, unroll: int = 1
) -> Callable[[PolicyParams, Array, Array, Array], CalOutput]:
    """A jitted ``run(params, w [U,T,W], x [U,T,S], mask [U,T]) -> CalOutput``.

    ``lax.scan`` over time, ``vmap`` over units
    (:func:`~jaxcal.baselines.interface.run_fleet`); compiled once per array shape.
    """

    def run(params: PolicyParams, w: Array, x: Array, mask: Array) -> CalOutput:
        calibrator = make_policy_calibrator(actor, dynamics, params)
        return run_fleet(calibrator, w, x, mask, unroll=unroll)

    return jax.jit(run)


def make_stream_step(
    actor: nn.Module, dynamics: Dynamics
) -> Callable[[PolicyParams, PolicyState, Array, Array], tuple[PolicyState, Array]]:
    """A jitted single-sample step ``(params, state, w [W], x [S]) -> (state, theta)``.

    The real-time path: one call per incoming sample.
    """

    def step(params: PolicyParams, state: PolicyState, w: Array, x: Array):
        new_state, out = make_policy_calibrator(actor, dynamics, params).step(
            state, w, x
        )
        return new_state, out.theta

    return jax.jit(step)
