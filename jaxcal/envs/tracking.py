"""The tracking MDP of model calibration (paper §3.1), gymnax-style.

The agent sets the model parameters theta so that the model output x-hat follows the
observed trajectory x of one unit:

* state s_t = [x-hat_t, x_{t+1}, w_{t+1}], each block normalised with training
  statistics;
* action a_t in [-1, 1]^P, mapped affinely to theta_{t+1} in [theta_low, theta_high]
  (the paper's absolute actions), or, with ``EnvConfig.action = "increment"``, a
  gated change of theta driven by the prediction error of the current sample
  (:mod:`jaxcal.envs.increment`: the state then carries theta and x-hat is the
  prediction of sample t with theta_{t-1});
* transition x-hat_{t+1} = dynamics(dyn_params, w_{t+1}, x-hat_t, theta_{t+1}), where
  ``dynamics`` is any pure callable: the learned surrogate D uses x-hat_t, the physics
  F(w, theta) ignores it. A model with memory carries its hidden state z [Z] in the
  env state: (z_{t+1}, x-hat_{t+1}) = step(z_t, w_{t+1}, theta_{t+1})
  (:class:`StatefulDynamics`, the state :class:`StatefulEnvState`); a plain callable
  is the stateful one with Z = 0, so the static path is the same code, its state the
  plain :class:`EnvState` rather than one with an empty z (Orbax refuses to
  checkpoint zero-size arrays, and so a static run's checkpoints keep the layout
  they had: older runs resume);
* cost c_t = mean_S ((x_{t+1} - x-hat_{t+1}) / sigma)^2, sigma = training std of x.

Episodes are windows of ``episode_length`` steps of one unit (random unit, random
start such that the window and its last next state fit the unit's valid length),
x-hat_0 = x_0 and z_0 = the reference state of that sample (``EnvParams.z_ref``, the
model state after the sample, computed by the training pipeline).
The data live in :class:`EnvParams` (so a new data set or surrogate is new input, not a
recompilation); static sizes live in :class:`EnvConfig`. The transition is wrapped in
``lax.stop_gradient`` unless ``EnvConfig.differentiable`` is set. ``step`` returns the
true next observation and ``done``; auto-reset is the runner's job.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxcal.envs.env_data import (  # noqa: F401 (re-exported: the env's data)
    EnvParams,
    compute_norm_stats,
    make_env_params,
)
from jaxcal.envs.increment import apply_increment, increment_observation
from jaxcal.envs.memory import StatefulDynamics, as_stateful  # noqa: F401 (re-export)
from jaxcal.typedefs import Array, PRNGKey, PyTree

Dynamics = Callable[[PyTree, Array, Array, Array], Array]
"""``dynamics(dyn_params, w_next [W], xhat [S], theta [P]) -> xhat_next [S]``."""


def check_action_options(
    action: str, max_increment: float, cost: str, cost_floor: float
) -> None:
    """Validates the action and cost options (:class:`EnvConfig`, and the training
    config's ``env.*`` fields before any work).

    Raises:
        ValueError: naming the ``env.`` field and its allowed values.
    """
    if action not in ("absolute", "increment"):
        raise ValueError(
            f"env.action must be 'absolute' or 'increment', got {action!r}"
        )
    if not 0.0 < max_increment <= 1.0:
        raise ValueError(f"env.max_increment must be in (0, 1], got {max_increment}")
    if cost not in ("squared", "log") or not cost_floor > 0:
        raise ValueError(
            "env.cost must be 'squared' or 'log' and env.cost_floor > 0, got "
            f"{cost!r}, {cost_floor}"
        )


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Static configuration of the tracking environment.

    Attributes:
        sensor_dim: S, number of observed outputs x.
        condition_dim: W, number of operating conditions w.
        param_dim: P, number of calibrated parameters theta.
        episode_length: steps per training episode (window length).
        differentiable: if True, gradients flow through the transition.
        action: ``"absolute"``: the action sets theta (the paper's); ``"increment"``:
            the action changes theta, gated by the residual
            (:mod:`jaxcal.envs.increment`).
        max_increment: the largest change of theta per step as a share of the box
            width (``action="increment"`` only).
        cost: ``"squared"``: c = mean_S ((x - x-hat) / sigma)^2 (the paper's);
            ``"log"``: log(1 + c / floor^2), which weighs a halving of the error the
            same at every scale (a feedback policy must keep contracting the error
            where the outputs barely see theta, at idle, not only where they do).
        cost_floor: the residual RMS below which the log cost is flat.
    """

    sensor_dim: int
    condition_dim: int
    param_dim: int
    episode_length: int = 100
    differentiable: bool = False
    action: str = "absolute"
    max_increment: float = 0.5
    cost: str = "squared"
    cost_floor: float = 1e-4

    def __post_init__(self) -> None:
        for name in ("sensor_dim", "condition_dim", "param_dim", "episode_length"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(
                    f"EnvConfig.{name} must be a positive int, got {value!r}"
                )
        check_action_options(
            self.action, self.max_increment, self.cost, self.cost_floor
        )

    @property
    def incremental(self) -> bool:
        """True when the action changes theta rather than setting it."""
        return self.action == "increment"

    @property
    def observation_size(self) -> int:
        """Size of s_t: 2 S + W ([x-hat_t, x_{t+1}, w_{t+1}]), or S + 1 + W + P for
        incremental actions ([r / |r|, lg |r|, w_{t+1}, theta_t])."""
        if self.incremental:
            return self.sensor_dim + 1 + self.condition_dim + self.param_dim
        return 2 * self.sensor_dim + self.condition_dim

    @property
    def min_unit_length(self) -> int:
        """Shortest unit a training window fits in: episode_length + 2 samples."""
        return self.episode_length + 2


def _check_dims(params: EnvParams, cfg: EnvConfig) -> None:
    # Shapes are static under tracing, so inside jit this runs once per compilation.
    for name, want in (
        ("x", cfg.sensor_dim),
        ("w", cfg.condition_dim),
        ("theta_low", cfg.param_dim),
    ):
        got = getattr(params, name).shape[-1]
        if want != got:
            raise ValueError(
                f"EnvParams.{name} has last dimension {got}, EnvConfig expects {want}"
            )


def check_env_params(params: EnvParams, cfg: EnvConfig) -> None:
    """Checks that ``params`` fit ``cfg``: dimensions, and window length when concrete.

    Raises:
        ValueError: if a dimension differs or no unit is long enough for one window.
    """
    _check_dims(params, cfg)
    if isinstance(params.lengths, jax.core.Tracer):
        return  # abstract evaluation (jit, eval_shape): only shapes can be checked
    longest = int(np.max(np.asarray(params.lengths)))
    if longest < cfg.min_unit_length:
        raise ValueError(
            f"no unit is long enough for episode_length={cfg.episode_length}: the "
            f"longest has {longest} rows, a window needs {cfg.min_unit_length}"
        )


@struct.dataclass
class EnvState:
    """State of one tracking episode (no PRNG key, gymnax rule).

    Attributes:
        unit: [] int32, unit index u.
        time: [] int32, index t of the current sample in the unit.
        step: [] int32, steps taken in this episode.
        xhat: [S] current model output x-hat_t (physical units).
    """

    unit: Array
    time: Array
    step: Array
    xhat: Array


@struct.dataclass
class StatefulEnvState(EnvState):
    """:class:`EnvState` of a model with memory.

    Attributes:
        z: [Z] model state after sample t.
    """

    z: Array


@struct.dataclass
class IncrementEnvState(EnvState):
    """:class:`EnvState` of incremental actions: theta_t [P] is carried."""

    theta: Array


@struct.dataclass
class StatefulIncrementEnvState(StatefulEnvState):
    """:class:`StatefulEnvState` of incremental actions: theta_t [P] is carried."""

    theta: Array


def _env_state(unit, time, step, xhat, z, theta=None) -> EnvState:
    """The state of a static model (``z is None``) or of one with memory, with
    theta when the actions are incremental (each its own class, so that the
    checkpoints of absolute-action runs keep their layout)."""
    fields = dict(unit=unit, time=time, step=step, xhat=xhat)
    if z is None:
        if theta is None:
            return EnvState(**fields)
        return IncrementEnvState(**fields, theta=theta)
    if theta is None:
        return StatefulEnvState(**fields, z=z)
    return StatefulIncrementEnvState(**fields, z=z, theta=theta)


class Env(NamedTuple):
    """The environment as pure functions (gymnax signature).

    Attributes:
        reset: ``reset(key, params) -> (obs [O], state)``.
        step: ``step(key, state, action [P], params) -> (obs, state, cost, done,
            info)``; ``info`` holds ``theta`` [P], ``terminated`` and ``truncated``.
        reset_at: ``reset_at(params, unit, time) -> (obs, state)``, a deterministic
            start at a given sample (evaluation over whole trajectories; incremental
            actions start from the box centre, as a deployed stream).
        observation_size: O (:attr:`EnvConfig.observation_size`).
        action_size: P.
        config: the static :class:`EnvConfig` the env was built with.
    """

    reset: Callable
    step: Callable
    reset_at: Callable
    observation_size: int
    action_size: int
    config: EnvConfig


def _row(data: Array, params: EnvParams, unit: Array, time: Array) -> Array:
    """``data[unit, time]``, the index clamped into the unit's valid rows."""
    return data[unit, jnp.clip(time, 0, params.lengths[unit] - 1)]


def observation(state: EnvState, params: EnvParams) -> Array:
    """s_t = [norm(x-hat_t), norm(x_{t+1}), norm(w_{t+1})] as float32 ``[2S + W]``."""
    x_next = _row(params.x, params, state.unit, state.time + 1)
    w_next = _row(params.w, params, state.unit, state.time + 1)
    obs = jnp.concatenate(
        [
            (state.xhat - params.x_mean) / params.x_std,
            (x_next - params.x_mean) / params.x_std,
            (w_next - params.w_mean) / params.w_std,
        ]
    )
    return obs.astype(jnp.float32)


def action_to_theta(action: Array, params: EnvParams) -> Array:
    """Affine map [-1, 1]^P -> [theta_low, theta_high]; actions outside are clipped."""
    unit_interval = 0.5 * (jnp.clip(action, -1.0, 1.0) + 1.0)
    return params.theta_low + unit_interval.astype(params.theta_low.dtype) * (
        params.theta_high - params.theta_low
    )


def tracking_cost(x: Array, xhat: Array, x_std: Array) -> Array:
    """c = mean_S ((x - x-hat) / sigma)^2 over the last axis (paper §3.1)."""
    return jnp.mean(jnp.square((x - xhat) / x_std), axis=-1)


def make_tracking_env(dynamics: Dynamics | StatefulDynamics, cfg: EnvConfig) -> Env:
    """Builds the tracking environment around a dynamics callable.

    Args:
        dynamics: pure ``(dyn_params, w_next [W], xhat [S], theta [P]) -> xhat_next
            [S]``, or a :class:`StatefulDynamics` for a model with memory;
            ``dyn_params`` is read from :attr:`EnvParams.dyn_params`.
        cfg: static sizes and episode length.

    Returns:
        :class:`Env`.
    """
    dyn = as_stateful(dynamics)

    def check(params: EnvParams) -> None:
        _check_dims(params, cfg)
        got = 0 if params.z_ref is None else params.z_ref.shape[-1]
        if got != dyn.num_states:
            raise ValueError(
                f"EnvParams.z_ref has {got} states (last dimension; None: 0), the "
                f"dynamics carry Z = {dyn.num_states}: build the params with "
                "make_env_params(..., z_ref=reference_states(...))"
            )
        if cfg.incremental and params.step_ref is None:
            raise ValueError(
                "env.action='increment' needs EnvParams.step_ref (the gate scale of "
                "each parameter): build the params with make_env_params(..., "
                "step_ref=...)"
            )

    def z_at(params: EnvParams, unit: Array, time: Array) -> Array | None:
        if not dyn.num_states:
            return None
        return _row(params.z_ref, params, unit, time)

    def theta_centre(params: EnvParams) -> Array:
        return 0.5 * (params.theta_low + params.theta_high)

    def observe(state: EnvState, params: EnvParams) -> Array:
        if not cfg.incremental:
            return observation(state, params)
        # predict-correct: x-hat is the prediction of sample t with theta_{t-1}
        x_now = _row(params.x, params, state.unit, state.time)
        w_now = _row(params.w, params, state.unit, state.time)
        return increment_observation(
            (x_now - state.xhat) / params.x_std,
            (w_now - params.w_mean) / params.w_std,
            state.theta,
            params.theta_low,
            params.theta_high,
        )

    def predict_first(params, unit, time, theta):
        # the prediction of sample t with theta_{t-1} = theta: the model from the
        # previous sample's reference state (x-hat of the surrogate: the previous
        # measurement)
        z_prev = z_at(params, unit, time - 1)
        x_prev = _row(params.x, params, unit, time - 1)
        w_now = _row(params.w, params, unit, time)
        z, xhat = dyn.step(params.dyn_params, z_prev, w_now, x_prev, theta)
        return jax.lax.stop_gradient((z, xhat.astype(x_prev.dtype)))

    def reset_at(
        params: EnvParams, unit: Array, time: Array, theta: Array | None = None
    ) -> tuple[Array, EnvState]:
        check(params)
        unit = jnp.asarray(unit, jnp.int32)
        time = jnp.asarray(time, jnp.int32)
        xhat = _row(params.x, params, unit, time)
        z = z_at(params, unit, time)
        if cfg.incremental:
            theta = theta_centre(params) if theta is None else theta
            z, xhat = predict_first(params, unit, time, theta)
        state = _env_state(
            unit=unit,
            time=time,
            step=jnp.zeros((), jnp.int32),
            xhat=xhat,
            z=None if z is None else z.astype(xhat.dtype),
            theta=theta if cfg.incremental else None,
        )
        return observe(state, params), state

    def reset(key: PRNGKey, params: EnvParams) -> tuple[Array, EnvState]:
        key_unit, key_start = jax.random.split(key)
        eligible = params.lengths >= cfg.min_unit_length
        unit = jax.random.choice(
            key_unit, eligible.shape[0], p=eligible / jnp.sum(eligible)
        )
        last_start = jnp.maximum(params.lengths[unit] - cfg.min_unit_length, 0)
        start = jax.random.randint(key_start, (), 0, last_start + 1)
        theta = None
        if cfg.incremental:  # episodes start anywhere in the box
            theta = jax.random.uniform(
                jax.random.fold_in(key, 1),
                params.theta_low.shape,
                params.theta_low.dtype,
                params.theta_low,
                params.theta_high,
            )
        return reset_at(params, unit, start, theta)

    def step(
        key: PRNGKey, state: EnvState, action: Array, params: EnvParams
    ) -> tuple[Array, EnvState, Array, Array, dict[str, Array]]:
        del key  # the transition is deterministic; kept for the gymnax signature
        check(params)
        if cfg.incremental:  # theta_t from the prediction error of sample t
            x_now = _row(params.x, params, state.unit, state.time)
            theta = apply_increment(
                action,
                state.theta,
                (x_now - state.xhat) / params.x_std,
                params.theta_low,
                params.theta_high,
                cfg.max_increment,
                params.step_ref,
            )
        else:
            theta = action_to_theta(action, params)
        time = state.time + 1
        w_next = _row(params.w, params, state.unit, time)
        z = getattr(state, "z", None)  # None: a static model's EnvState
        z, xhat = dyn.step(params.dyn_params, z, w_next, state.xhat, theta)
        if not cfg.differentiable:
            z, xhat = jax.lax.stop_gradient((z, xhat))
        target = params.x if params.x_target is None else params.x_target
        cost = tracking_cost(_row(target, params, state.unit, time), xhat, params.x_std)
        if cfg.cost == "log":
            cost = jnp.log1p(cost / cfg.cost_floor**2)
        next_state = _env_state(
            unit=state.unit,
            time=time,
            step=state.step + 1,
            xhat=xhat.astype(state.xhat.dtype),
            z=None if z is None else z.astype(state.z.dtype),
            theta=theta if cfg.incremental else None,
        )
        done = next_state.step >= cfg.episode_length
        info = {"theta": theta, "terminated": jnp.zeros((), bool), "truncated": done}
        return (
            observe(next_state, params),
            next_state,
            cost.astype(jnp.float32),
            done,
            info,
        )

    return Env(reset, step, reset_at, cfg.observation_size, cfg.param_dim, cfg)
