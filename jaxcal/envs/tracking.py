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
  (:class:`StatefulDynamics`, the state :class:`.env_state.StatefulEnvState`); a
  plain callable is the stateful one with Z = 0, so the static path is the same code,
  its state the plain :class:`EnvState` rather than one with an empty z (Orbax
  refuses to checkpoint zero-size arrays, and so a static run's checkpoints keep the
  layout they had: older runs resume);
* cost c_t = mean_S ((x_{t+1} - x-hat_{t+1}) / sigma)^2, sigma = training std of x.

Episodes are windows of ``episode_length`` steps of one unit (random unit, random
start such that the window and its last next state fit the unit's valid length),
x-hat_0 = x_0 and z_0 = the reference state of that sample (``EnvParams.z_ref``, the
model state after the sample, computed by the training pipeline).
The data live in :class:`EnvParams` (so a new data set or surrogate is new input, not a
recompilation); static sizes live in :class:`EnvConfig`. The transition is wrapped in
``lax.stop_gradient`` unless ``EnvConfig.differentiable`` is set. ``step`` returns the
true next observation and ``done``; auto-reset is the runner's job. The static
configuration and its checks are in :mod:`.env_config`, the state classes and the
:class:`Env` record in :mod:`.env_state`.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxcal.envs.env_config import (  # noqa: F401 (re-exported: the env's config)
    EnvConfig,
    check_action_options,
    check_dims,
    check_env_params,
)
from jaxcal.envs.env_data import (  # noqa: F401 (re-exported: the env's data)
    EnvParams,
    make_env_params,
)
from jaxcal.envs.env_state import (  # noqa: F401 (re-exported: the env's state)
    Env,
    EnvState,
    make_env_state,
)
from jaxcal.envs.increment import (
    adapted_noise_scale,
    apply_increment,
    filter_feature,
    gauss_newton_features,
    increment_observation,
    initial_filter_cov,
    initial_noise_scale,
    step_with_sensitivity,
)
from jaxcal.envs.joint_filter import (
    conditioned_state,
    initial_joint_cov,
    joint_filter_feature,
    joint_prior,
    step_with_joint,
)
from jaxcal.envs.memory import StatefulDynamics, as_stateful  # noqa: F401 (re-export)
from jaxcal.typedefs import Array, PRNGKey, PyTree

Dynamics = Callable[[PyTree, Array, Array, Array], Array]
"""``dynamics(dyn_params, w_next [W], xhat [S], theta [P]) -> xhat_next [S]``."""


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


def _check_params(params: EnvParams, cfg: EnvConfig, dyn: StatefulDynamics) -> None:
    """Dimensions against ``cfg``; the reference states and the gate scale the
    dynamics and the action kind need (static: runs once per trace)."""
    check_dims(params, cfg)
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
    if cfg.gn_filter and params.x_noise is None:
        raise ValueError(
            "env.gn_filter needs EnvParams.x_noise (the measurement noise std of "
            "each output, [S]): build the params with x_noise=problem.noise_std"
        )


def _z_at(dyn: StatefulDynamics, params: EnvParams, unit, time) -> Array | None:
    """The reference model state after sample ``time`` (``None``: a static model)."""
    if not dyn.num_states:
        return None
    return _row(params.z_ref, params, unit, time)


def _observe(
    cfg: EnvConfig, state: EnvState, params: EnvParams, jac=None, filtered=None
) -> Array:
    """The agent's observation: :func:`observation`, or for incremental actions the
    residual of the current sample (predict-correct: x-hat is the prediction of
    sample t with theta_{t-1}), with ``gauss_newton`` its step through ``jac``, the
    prediction's Jacobian, with ``gn_filter`` the filter's step ``filtered``, and
    the window's age."""
    if not cfg.incremental:
        return observation(state, params)
    x_now = _row(params.x, params, state.unit, state.time)
    w_now = _row(params.w, params, state.unit, state.time)
    resid = (x_now - state.xhat) / params.x_std
    extra = None
    if cfg.uses_jacobian:  # the age: samples since the window's start
        extra = gauss_newton_features(
            resid, jac, state.step, params, cfg.max_increment,
            one_sample=cfg.gauss_newton, filtered=filtered,
        )  # fmt: skip
    return increment_observation(
        resid,
        (w_now - params.w_mean) / params.w_std,
        state.theta,
        params.theta_low,
        params.theta_high,
        extra,
    )


def _model_step(
    cfg: EnvConfig,
    dyn: StatefulDynamics,
    params: EnvParams,
    z,
    w,
    xhat,
    theta,
    sens,
    joint: bool = False,
):
    """``(z, x-hat, J, sens, AH)`` of one model step; with ``gauss_newton`` J is its
    Jacobian in theta and ``sens`` the state's sensitivity carried
    (:func:`~jaxcal.envs.increment.step_with_sensitivity`), else both ``None``;
    ``joint``: ``AH`` the step's Jacobians in (state, theta) for the joint filter
    (:func:`~jaxcal.envs.joint_filter.step_with_joint`), else ``None``."""
    if not cfg.uses_jacobian:
        return (*dyn.step(params.dyn_params, z, w, xhat, theta), None, None, None)

    def one(z_, th):
        return dyn.step(params.dyn_params, z_, w, xhat, th)

    if joint:
        half = 0.5 * (params.theta_high - params.theta_low)
        jac, sens, ah, z, xhat = step_with_joint(one, z, theta, sens, half)
        return z, xhat, *jax.lax.stop_gradient((jac, sens, ah))
    jac, sens, z, xhat = step_with_sensitivity(one, z, theta, sens)
    return z, xhat, *jax.lax.stop_gradient((jac, sens)), None


def _predict_first(
    cfg, dyn: StatefulDynamics, params: EnvParams, unit, time, theta, joint=False
):
    """(z, x-hat, J, sens, AH) of sample ``time`` predicted with theta_{t-1} =
    ``theta``: the model from the previous sample's reference state (x-hat of the
    surrogate: the previous measurement); J and sens as :func:`_model_step`, the
    reference state's sensitivity taken as zero."""
    z_prev = _z_at(dyn, params, unit, time - 1)
    x_prev = _row(params.x, params, unit, time - 1)
    w_now = _row(params.w, params, unit, time)
    sens = None
    if cfg.uses_jacobian and dyn.num_states:
        sens = jnp.zeros((dyn.num_states, theta.shape[-1]), x_prev.dtype)
    out = _model_step(cfg, dyn, params, z_prev, w_now, x_prev, theta, sens, joint)
    z, xhat, jac, sens, ah = jax.lax.stop_gradient(out)
    return z, xhat.astype(x_prev.dtype), jac, sens, ah


def _prior_cov(cfg: EnvConfig, num_states: int, dtype, joint: bool) -> Array:
    """A stream's first filter covariance: theta's, or the joint one of state and
    theta (:mod:`jaxcal.envs.joint_filter`)."""
    if joint:
        return initial_joint_cov(num_states, cfg.param_dim, dtype, cfg.filter_prior_std)
    return initial_filter_cov(cfg.param_dim, dtype, cfg.filter_prior_std)


def _filtered(
    cfg: EnvConfig, params: EnvParams, unit, time, xhat, jac, cov, z, ah, scale=None
):
    """``(z, cov', step, du, scale')`` of the filter step at sample ``time``
    (``gn_filter``; :func:`~jaxcal.envs.increment.filter_feature`, or with the joint
    Jacobians ``ah`` :func:`~jaxcal.envs.joint_filter.joint_filter_feature`, the
    only one that corrects the state ``z`` and has a theta step ``du``), else ``z``
    and ``None``. ``scale``: the adaptive filter's noise scale
    (``EnvConfig.filter_adapt``, the filter on theta alone), ``scale'`` its update
    by this sample."""
    if not cfg.gn_filter:
        return z, None, None, None, None
    resid = (_row(params.x, params, unit, time) - xhat) / params.x_std
    if ah is not None:
        out = joint_filter_feature(
            cov, resid, ah, params, cfg.max_increment, cfg.filter_q
        )
        new_cov, feature, dz, du = jax.lax.stop_gradient(out)
        return z + dz.astype(z.dtype), new_cov, feature, du, None
    out = filter_feature(
        cov, resid, jac, params, cfg.max_increment, cfg.filter_q, cfg.filter_whole,
        scale,
    )  # fmt: skip
    if scale is not None:
        scale = jax.lax.stop_gradient(
            adapted_noise_scale(scale, resid, jac, params, cfg.filter_adapt)
        )
    return (z, *jax.lax.stop_gradient(out), None, scale)


def _draw_start(key: PRNGKey, params: EnvParams, cfg: EnvConfig):
    """A random episode start: (unit, start, theta_0), the unit among those a
    window fits, theta_0 anywhere in the box for incremental actions (else None)."""
    key_unit, key_start = jax.random.split(key)
    eligible = params.lengths >= cfg.min_unit_length
    unit = jax.random.choice(
        key_unit, eligible.shape[0], p=eligible / jnp.sum(eligible)
    )
    last_start = jnp.maximum(params.lengths[unit] - cfg.min_unit_length, 0)
    start = jax.random.randint(key_start, (), 0, last_start + 1)
    theta = None
    if cfg.incremental:
        theta = jax.random.uniform(
            jax.random.fold_in(key, 1),
            params.theta_low.shape,
            params.theta_low.dtype,
            params.theta_low,
            params.theta_high,
        )
    return unit, start, theta


def _next_theta(cfg: EnvConfig, state: EnvState, action, params: EnvParams):
    """theta_{t+1} from the action: set (absolute) or changed by the gated
    increment driven by the prediction error of sample t."""
    if not cfg.incremental:
        return action_to_theta(action, params)
    x_now = _row(params.x, params, state.unit, state.time)
    return apply_increment(
        action,
        state.theta,
        (x_now - state.xhat) / params.x_std,
        params.theta_low,
        params.theta_high,
        cfg.max_increment,
        params.step_ref,
    )


def _step_cost(
    cfg: EnvConfig, params: EnvParams, unit, time, xhat, theta=None
) -> Array:
    """The cost of x-hat at sample ``time`` against the target (x unless
    ``EnvParams.x_target``), with the theta term where the true theta is known
    (``EnvConfig.theta_cost``), squared or log (:class:`EnvConfig`)."""
    target = params.x if params.x_target is None else params.x_target
    cost = tracking_cost(_row(target, params, unit, time), xhat, params.x_std)
    if cfg.theta_cost and params.theta_target is not None and theta is not None:
        cost = cost + cfg.theta_cost * theta_error_cost(
            theta, _row(params.theta_target, params, unit, time), params
        )
    if cfg.cost == "log":
        cost = jnp.log1p(cost / cfg.cost_floor**2)
    return cost


def theta_error_cost(theta: Array, truth: Array, params: EnvParams) -> Array:
    """``mean_P(((theta - truth) / h)^2)`` over the parameters whose truth is known
    (finite), ``h`` the box's half-widths; 0 where none is."""
    half = 0.5 * (params.theta_high - params.theta_low)
    known = jnp.isfinite(truth)
    err = jnp.where(known, (theta - jnp.where(known, truth, 0.0)) / half, 0.0)
    return jnp.sum(jnp.square(err)) / jnp.maximum(jnp.sum(known), 1)


def make_tracking_env(dynamics: Dynamics | StatefulDynamics, cfg: EnvConfig) -> Env:
    """Builds the tracking environment around a dynamics callable.

    Args:
        dynamics: pure ``(dyn_params, w_next [W], xhat [S], theta [P]) -> xhat_next
            [S]``, or a :class:`StatefulDynamics` for a model with memory;
            ``dyn_params`` is read from :attr:`EnvParams.dyn_params`.
        cfg: static sizes and episode length.
    """
    dyn = as_stateful(dynamics)
    # a model with memory under the whole filter: state and theta filtered jointly
    joint = cfg.gn_filter and cfg.filter_whole and dyn.num_states > 0

    def reset_at(
        params: EnvParams, unit: Array, time: Array, theta: Array | None = None
    ) -> tuple[Array, EnvState]:
        _check_params(params, cfg, dyn)
        unit = jnp.asarray(unit, jnp.int32)
        time = jnp.asarray(time, jnp.int32)
        xhat = _row(params.x, params, unit, time)
        z = _z_at(dyn, params, unit, time)
        jac = sens = None
        if cfg.incremental:  # deterministic starts: from the box centre
            if theta is None:
                theta = 0.5 * (params.theta_low + params.theta_high)
            z, xhat, jac, sens, ah = _predict_first(
                cfg, dyn, params, unit, time, theta, joint
            )
        cov = filtered = fstep = scale = None
        if cfg.gn_filter:
            prior = _prior_cov(cfg, dyn.num_states, params.theta_low.dtype, joint)
            if joint:  # the first state's dependence on theta, as a stream's
                half = 0.5 * (params.theta_high - params.theta_low)
                w_t = _row(params.w, params, unit, time).astype(prior.dtype)
                prior = joint_prior(
                    dyn, params.dyn_params, w_t, theta.astype(prior.dtype), prior, half
                )
            z, cov, filtered, fstep, scale = _filtered(
                cfg, params, unit, time, xhat, jac, prior, z, ah,
                initial_noise_scale(
                    cfg.gn_filter, cfg.filter_adapt, dyn.num_states, xhat
                ),
            )  # fmt: skip
        state = make_env_state(
            unit=unit,
            time=time,
            step=jnp.zeros((), jnp.int32),
            xhat=xhat,
            z=None if z is None else z.astype(xhat.dtype),
            theta=theta if cfg.incremental else None,
            sens=sens,
            cov=cov,
            fstep=fstep,
            noise_scale=scale,
        )
        return _observe(cfg, state, params, jac, filtered), state

    def reset(key: PRNGKey, params: EnvParams) -> tuple[Array, EnvState]:
        unit, start, theta = _draw_start(key, params, cfg)
        return reset_at(params, unit, start, theta)

    def step(
        key: PRNGKey, state: EnvState, action: Array, params: EnvParams
    ) -> tuple[Array, EnvState, Array, Array, dict[str, Array]]:
        del key  # the transition is deterministic; kept for the gymnax signature
        _check_params(params, cfg, dyn)
        theta = _next_theta(cfg, state, action, params)
        time = state.time + 1
        w_next = _row(params.w, params, state.unit, time)
        z = getattr(state, "z", None)  # None: a static model's EnvState
        sens = getattr(state, "sens", None)  # with gauss_newton on a model with memory
        if joint:  # the filter's state, given the policy's theta step
            half = 0.5 * (params.theta_high - params.theta_low)
            z = conditioned_state(
                z, state.cov, (theta - state.theta) / half, state.fstep
            )
        z, xhat, jac, sens, ah = _model_step(
            cfg, dyn, params, z, w_next, state.xhat, theta, sens, joint
        )
        if not cfg.differentiable:
            z, xhat = jax.lax.stop_gradient((z, xhat))
        cost = _step_cost(cfg, params, state.unit, time, xhat, theta)
        z, cov, filtered, fstep, scale = _filtered(
            cfg, params, state.unit, time, xhat.astype(state.xhat.dtype), jac,
            getattr(state, "cov", None), z, ah, getattr(state, "noise_scale", None),
        )  # fmt: skip
        next_state = make_env_state(
            unit=state.unit,
            time=time,
            step=state.step + 1,
            xhat=xhat.astype(state.xhat.dtype),
            z=None if z is None else z.astype(state.z.dtype),
            theta=theta if cfg.incremental else None,
            sens=None if sens is None else sens.astype(state.sens.dtype),
            cov=cov,
            fstep=fstep,
            noise_scale=scale,
        )
        done = next_state.step >= cfg.episode_length
        info = {"theta": theta, "terminated": jnp.zeros((), bool), "truncated": done}
        obs = _observe(cfg, next_state, params, jac, filtered)
        return obs, next_state, cost.astype(jnp.float32), done, info

    return Env(reset, step, reset_at, cfg.observation_size, cfg.param_dim, cfg)
