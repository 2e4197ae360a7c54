"""The deployed policy's step as a :class:`~jaxcal.calibrators.interface.Calibrator`
(:func:`make_policy_calibrator`).

Deployment of the paper's policy (§3.1, "Implementation stage"): with the model output
x-hat_{t-1} carried in the state, each new sample (w_t, x_t) gives

    s = [norm(x-hat_{t-1}), norm(x_t), norm(w_t)],   theta_t = box(pi*(s)),
    x-hat_t = D(w_t, x-hat_{t-1}, theta_t),

with pi* = tanh(mean) the deterministic policy and ``box`` the environment's affine map
to [theta_low, theta_high]. This is the training environment's step shifted by one
index, so on samples t >= 1 the calibrator reproduces the environment's deterministic
rollout (``tests/support/policy_rollout.py``). On the first sample there is no x-hat
yet: x-hat = x_0 (as the environment's reset), theta_0 = box(pi*([norm(x_0), norm(x_0),
norm(w_0)])) and x-hat_0 = x_0.

With incremental actions (:class:`IncrementPolicyParams`, ``env.action=increment``,
:mod:`jaxcal.envs.increment`) the state carries theta_{t-1}, and each sample is
predicted, then corrected:

    x-hat_t = F(w_t, theta_{t-1}),  r = (x_t - x-hat_t) / sigma_x,
    s = [r / |r|, lg |r|, norm(w_t), theta_{t-1}],
    theta_t = clip(theta_{t-1} + M pi*(s) |r| / (|r| + n_ref), box);

one model evaluation per sample, theta_{-1} = the box centre (the environment's
``reset_at``), and x-hat_t is the one-step prediction.

A model with memory (:class:`~jaxcal.envs.memory.StatefulDynamics`) also carries its
state z: (z_t, x-hat_t) = step(z_{t-1}, w_t, x-hat_{t-1}, theta_t), and the first
sample sets z_0 = init(w_0), the state after w_0 with the prior theta (the training
environment's reference state at t = 0 is the same, so on whole trajectories the two
still agree). A static model carries ``z = None``.

A static model with a warm start (:class:`~jaxcal.envs.memory.HintedDynamics`, e.g.
the turbofan's Newton solve) may also carry its solver hint from sample to sample
(``warm_start=True``, ``PolicyState.hint``): x-hat is then the model's output to its
solver tolerance, at a fraction of the cold solve's cost; the first sample starts
without one. The deployed stream and the fleet runner
(:func:`~jaxcal.calibrators.methods.policy.calibrator.make_fleet_runner`: the turbofan's
hinted solve batches with a rule of its own, the cold fall-back only at rows some unit
needs it) do; the paper's scored methods keep the cold solve (and the paper's bits).

What the step reads and carries
(:class:`~jaxcal.calibrators.methods.policy.params.PolicyParams`,
:class:`~jaxcal.calibrators.methods.policy.params.PolicyState`) is in
:mod:`jaxcal.calibrators.methods.policy.params`; the jitted runners over fleets and
streams are in :mod:`jaxcal.calibrators.methods.policy.calibrator`, which re-exports
both modules' names.
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxcal.calibrators.interface import Calibrator, CalStepOutput
from jaxcal.calibrators.methods.policy.params import (
    IncrementPolicyParams,
    PolicyParams,
    PolicyState,
    counts,
    has_bias_states,
    initial_sensitivity,
    uses_jacobian,
)
from jaxcal.calibrators.uncertainty.conformal import ThetaBand, band_std
from jaxcal.calibrators.uncertainty.lag_scale import (
    filter_error_scale,
    initial_trend,
    trend_rate,
    update_trend,
)
from jaxcal.envs.bias_states import (
    bias_rate,
    bias_walk,
    biased_jacobians,
    debiased,
    static_joint,
    with_bias_block,
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
from jaxcal.envs.memory import HintedDynamics, StatefulDynamics, as_stateful
from jaxcal.envs.tracking import Dynamics, action_to_theta
from jaxcal.typedefs import Array, PRNGKey


def make_policy_calibrator(
    actor: nn.Module,
    dynamics: Dynamics | StatefulDynamics,
    params: PolicyParams,
    band: ThetaBand | None = None,
    *,
    warm_start: bool = False,
    start_at_first_sample: bool = True,
) -> Calibrator:
    """The deterministic policy pi* and the dynamics as ``Calibrator(init, step)``.

    Args:
        actor: the agent's actor module (``apply(params, obs) -> (mean, log_std)``).
        dynamics: ``dynamics(dyn_params, w [W], xhat [S], theta [P]) -> xhat [S]``,
            or a :class:`~jaxcal.envs.memory.StatefulDynamics`.
        params: :class:`PolicyParams` (may be traced).
        band: the run's calibrated error band
            (:mod:`jaxcal.calibrators.uncertainty.conformal`, fitted on its validation
            units); ``None``: no uncertainty. A relative band scales the error the
            policy's filter predicts (:func:`filter_scale`; an incremental policy
            with the filter feature only).
        warm_start: carry the model's solver hint from sample to sample (a
            :class:`~jaxcal.envs.memory.HintedDynamics`; ignored otherwise): a
            stream, one sample per call, and a fleet (the turbofan's hinted solve
            batches with a rule of its own,
            ``jaxcal.models.turbofan.physics.warm_start``).
        start_at_first_sample: a model with memory starts its state at the first
            sample the step is fed (a stream whose first state was made before any
            row). ``False`` where ``init`` is given the first ok row, as
            ``run_calibrator`` does: the state ``init`` made is that start already,
            and over a fleet (under ``vmap``) the step would compute the start at
            every row only to discard it.

    Returns:
        A :class:`~jaxcal.calibrators.interface.Calibrator`; ``aux`` is
        ``{"theta_std": [P]}`` (the band's std at the sample's index in the stream)
        with a band, else ``None``. It does not accept partial rows: a row with some
        outputs missing (NaN) is skipped by the runners with reason ``x_partial``
        (the network's input is the whole normalised ``x_t``; imputing the missing
        output with x-hat would feed back the policy's own prediction as if
        measured).
    """
    dyn = as_stateful(dynamics)
    incremental = isinstance(params, IncrementPolicyParams)
    if band is not None and band.relative and not getattr(params, "gn_filter", False):
        raise ValueError(
            "a relative band scales the error the policy's filter predicts: it needs "
            "an incremental policy with the filter feature (env.gauss_newton=filter)"
        )
    hinted = warm_start and isinstance(dynamics, HintedDynamics)
    transition = _make_transition(dyn, dynamics, params, hinted)
    first_state = functools.partial(_first_state, dyn, params)
    if not start_at_first_sample:
        first_state = _kept_state
    sample_step = _absolute_step
    if incremental:  # a model with memory under the whole filter: the joint filter
        joint = params.gn_filter and params.filter_whole and dyn.num_states > 0
        first_cov = _kept_cov
        if joint and start_at_first_sample:
            first_cov = functools.partial(_first_cov, dyn, params)
        sample_step = functools.partial(
            _increment_step, joint=joint, first_cov=first_cov
        )
    advance = functools.partial(sample_step, actor, params, transition, first_state)

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> PolicyState:
        del key  # deterministic; x-hat starts at the first measurement
        return _initial_state(dyn, dynamics, params, band, hinted, w0, x0)

    def step(
        state: PolicyState, w_t: Array, x_t: Array
    ) -> tuple[PolicyState, CalStepOutput]:
        new_state, theta, xhat = advance(state, w_t, x_t)
        if state.count is not None:
            new_state = new_state.replace(count=state.count + 1)
        if band is None:
            return new_state, CalStepOutput(theta=theta, xhat=xhat)
        scale = None
        if band.relative:
            trend = update_trend(state.trend, state.started, theta)
            new_state = new_state.replace(trend=trend)
            scale = filter_scale(params, new_state.cov, trend)
        std = band_std(band, state.count, scale).astype(theta.dtype)
        return new_state, CalStepOutput(theta=theta, xhat=xhat, aux={"theta_std": std})

    return Calibrator(init, step)


def filter_scale(params: PolicyParams, cov: Array, trend: Array) -> Array:
    """``[P]`` the theta error the policy's filter predicts after a sample: its std
    and the lag bias of the drift ``trend`` shows
    (:func:`~jaxcal.calibrators.uncertainty.lag_scale.filter_error_scale`; a joint
    filter's theta block is its last ``P`` rows)."""
    num = params.theta_low.shape[-1]
    half = 0.5 * (params.theta_high - params.theta_low)
    return filter_error_scale(
        cov[-num:, -num:], trend_rate(trend), half.astype(cov.dtype), params.filter_q
    ).astype(trend.dtype)


def _make_transition(dyn: StatefulDynamics, dynamics, params: PolicyParams, hinted):
    """``transition(state, z, w_t, xhat_prev, theta) -> (z, x-hat, hint)``: one model
    step, warm-started from ``state.hint`` when the model can (``hinted``)."""

    def transition(state: PolicyState, z, w_t, xhat_prev, theta):
        if not hinted:
            return (*dyn.step(params.dyn_params, z, w_t, xhat_prev, theta), None)
        hint, xhat = dynamics.step(params.dyn_params, state.hint, w_t, xhat_prev, theta)
        return z, xhat, hint

    return transition


def _initial_state(
    dyn: StatefulDynamics, dynamics, params: PolicyParams, band, hinted, w0, x0
) -> PolicyState:
    """The state before the first sample: x-hat = x_0, the model state init(w_0),
    an incremental policy's start theta (the run's, else the box centre: the env's
    ``reset_at``), the band's sample count and the model's first solver hint."""
    z0 = dyn.init(params.dyn_params, w0.astype(x0.dtype))
    z0 = None if z0 is None else z0.astype(x0.dtype)
    hint = dynamics.init_hint() if hinted else None
    state = fresh_state(params, band, dyn.num_states, x0, z0, hint)
    if state.cov is None or not (params.filter_whole and dyn.num_states):
        return state
    return state.replace(cov=_joint_prior_at(dyn, params, w0))


def _joint_prior_at(dyn, params: PolicyParams, w):
    """The joint filter's first covariance at a stream's first conditions ``w``
    (:func:`~jaxcal.envs.joint_filter.joint_prior`, around the start theta), the
    output biases' block (known zeros) inserted where the filter has one."""
    cov = initial_cov(params, dyn.num_states, with_bias=False)
    half = 0.5 * (params.theta_high - params.theta_low)
    theta0 = start_theta(params).astype(cov.dtype)
    cov = joint_prior(dyn, params.dyn_params, w.astype(cov.dtype), theta0, cov, half)
    if not has_bias_states(params):
        return cov
    return with_bias_block(cov, dyn.num_states, params.x_noise.shape[0])


def fresh_state(params: PolicyParams, band, num_states: int, xhat, z, hint):
    """A :class:`PolicyState` before a stream's first sample, every field the step
    carries set in one place (the batch's first state and the streaming
    calibrator's first carry alike): x-hat and the model state as given, the
    start theta, the band's count and drift trend, the filter's sensitivity and
    covariance."""
    return PolicyState(
        xhat=xhat, started=jnp.zeros((), bool), z=z, theta=start_theta(params),
        count=jnp.zeros((), jnp.int32) if counts(params, band) else None,
        hint=hint, sens=initial_sensitivity(params, num_states, xhat.dtype),
        cov=initial_cov(params, num_states), trend=band_trend(params, band),
        noise_scale=initial_noise_scale(
            getattr(params, "gn_filter", False), getattr(params, "filter_adapt", 0),
            num_states, xhat,
        ),
        bias=jnp.zeros_like(xhat) if has_bias_states(params) else None,
    )  # fmt: skip


def start_theta(params: PolicyParams) -> Array | None:
    """An incremental policy's theta before its first sample: the run's start (the
    prior under ``env.start=prior``), else the box centre (the env's ``reset_at``);
    ``None`` for an absolute policy. The batch and the streaming calibrator both
    start here, so they agree from the first sample."""
    if not isinstance(params, IncrementPolicyParams):
        return None
    theta0 = getattr(params, "theta_start", None)
    return 0.5 * (params.theta_low + params.theta_high) if theta0 is None else theta0


def band_trend(params: PolicyParams, band) -> Array | None:
    """A stream's first drift-rate state for a relative band, else ``None``."""
    if band is None or not band.relative:
        return None
    return initial_trend(params.theta_low.shape[-1], params.theta_low.dtype)


def initial_cov(
    params: PolicyParams, num_states: int, with_bias: bool = True
) -> Array | None:
    """The filter step's first covariance (``gn_filter``; the joint one on a model
    with memory under ``filter_whole``; with the output biases' block where the
    filter has one, unless ``with_bias=False``), else ``None``."""
    if not getattr(params, "gn_filter", False):
        return None
    dims = (params.theta_low.shape[-1], params.theta_low.dtype, params.filter_prior_std)
    joint = params.filter_whole and num_states
    cov = initial_joint_cov(num_states, *dims) if joint else initial_filter_cov(*dims)
    if not (with_bias and has_bias_states(params)):
        return cov
    return with_bias_block(cov, num_states if joint else 0, params.x_noise.shape[0])


def _kept_cov(state: PolicyState, w_t):
    """The filter's covariance as carried."""
    return state.cov


def _first_cov(dyn, params: PolicyParams, state: PolicyState, w_t):
    """The joint filter's covariance, or at a stream's first sample its prior at
    that sample's conditions (the state's start, :func:`_first_state`, is made
    there too)."""

    def first():
        return _joint_prior_at(dyn, params, w_t)

    return jax.lax.cond(state.started, lambda: state.cov, first)


def _kept_state(state: PolicyState, z, w_t, x_t):
    """``z`` as carried (``init`` made the start from the first ok row)."""
    return z


def _first_state(dyn, params: PolicyParams, state: PolicyState, z, w_t, x_t):
    """``z``, or before any sample the model state init(w_0) (the env's
    ``z_ref[0]``); ``None`` for a static model."""
    if not dyn.num_states:
        return z

    def first():
        return dyn.init(params.dyn_params, w_t.astype(x_t.dtype)).astype(z.dtype)

    # a branch, not a select: the model's start (a settling run, a steady-state
    # solve) would otherwise be computed at every sample of a stream to be thrown
    # away (under vmap, over a fleet, the branch becomes a select again)
    return jax.lax.cond(state.started, lambda: z, first)


def _absolute_step(actor, params, transition, first_state, state, w_t, x_t):
    """``(state, theta_t, x-hat_t)`` of an absolute action: theta_t = box(pi*(s)) with
    s = [norm(x-hat_{t-1}), norm(x_t), norm(w_t)], then the model step to x-hat_t
    (the first sample: x-hat = x_0 and the state init(w_0))."""
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
    z, xhat, hint = transition(state, state.z, w_t, xhat_prev, theta)
    xhat = jnp.where(state.started, xhat.astype(x_t.dtype), x_t)
    z = first_state(state, z, w_t, x_t)  # the first sample's: init
    new_state = PolicyState(xhat=xhat, started=jnp.ones((), bool), z=z, hint=hint)
    return new_state, theta, xhat


def _increment_step(
    actor, params, transition, first_state, state, w_t, x_t, joint=False,
    first_cov=_kept_cov,
):  # fmt: skip
    """``(state, theta_t, x-hat_t)`` of an incremental action: predict sample t with
    theta_{t-1}, then correct theta on its error (:mod:`jaxcal.envs.increment`;
    ``joint``: the state too, :mod:`jaxcal.envs.joint_filter`)."""
    xhat_prev = jnp.where(state.started, state.xhat, x_t)
    z_prev = first_state(state, state.z, w_t, x_t)
    extra = sens = cov = joint_step = noise_scale = None
    half = 0.5 * (params.theta_high - params.theta_low)
    biased = has_bias_states(params)  # the output biases filtered with theta
    if uses_jacobian(params):  # the environment's observation (jaxcal.envs.increment)

        def one(z_, th):
            return transition(state, z_, w_t, xhat_prev, th)

        if joint:
            jac, sens, ah, z, xhat, hint = step_with_joint(
                one, z_prev, state.theta, state.sens, half
            )
            state = state.replace(cov=first_cov(state, w_t))
        else:
            jac, sens, z, xhat, hint = step_with_sensitivity(
                one, z_prev, state.theta, state.sens
            )
        resid = (x_t - xhat.astype(x_t.dtype)) / params.x_std
        filtered = None
        if biased:
            resid = debiased(resid, state.bias, params.x_noise, params.x_std)
            ah = biased_jacobians(
                ah if joint else static_joint(jac, half), params.x_noise,
                half.shape[-1],
            )  # fmt: skip
            walk = bias_walk(
                0 if z is None else z.shape[0],
                bias_rate(params.filter_bias_var, state.noise_scale),
                state.cov.dtype,
            )
            cov, filtered, dzb, du = joint_filter_feature(
                state.cov, resid, ah, params, params.max_increment, params.filter_q,
                walk, state.noise_scale,
            )  # fmt: skip
            joint_step = (dzb, du)
        elif joint:
            cov, filtered, dz, du = joint_filter_feature(
                state.cov, resid, ah, params, params.max_increment, params.filter_q
            )
            joint_step = (dz, du)
        elif params.gn_filter:
            cov, filtered = filter_feature(
                state.cov, resid, jac, params, params.max_increment,
                params.filter_q, params.filter_whole, state.noise_scale,
            )  # fmt: skip
        if state.noise_scale is not None:  # the filter on theta alone adapts
            noise_scale = adapted_noise_scale(
                state.noise_scale, resid, jac, params, params.filter_adapt
            )
        extra = gauss_newton_features(
            resid, jac, state.count, params, params.max_increment,
            one_sample=params.gauss_newton, filtered=filtered,
        )  # fmt: skip
    else:
        z, xhat, hint = transition(state, z_prev, w_t, xhat_prev, state.theta)
    xhat = xhat.astype(x_t.dtype)
    resid = (x_t - xhat) / params.x_std
    if biased:  # the innovation the filter read: the prediction plus the biases
        resid = debiased(resid, state.bias, params.x_noise, params.x_std)
    obs = increment_observation(
        resid,
        (w_t - params.w_mean) / params.w_std,
        state.theta,
        params.theta_low,
        params.theta_high,
        extra,
    )
    mean, _ = actor.apply(params.actor, obs)
    theta = apply_increment(
        jnp.tanh(mean),
        state.theta,
        resid,
        params.theta_low,
        params.theta_high,
        params.max_increment,
        params.step_ref,
    )
    bias = state.bias
    if biased:  # the (state, biases), given the policy's theta step
        dzb, du = joint_step
        zb = bias if z is None else jnp.concatenate([z, bias.astype(z.dtype)])
        zb = zb + dzb.astype(zb.dtype)
        zb = conditioned_state(zb, cov, (theta - state.theta) / half, du)
        num_states = zb.shape[0] - bias.shape[0]
        bias = zb[num_states:].astype(bias.dtype)
        z = None if z is None else zb[:num_states].astype(z.dtype)
    elif joint_step is not None:  # the filter's state, given the policy's theta step
        dz, du = joint_step
        z = z + dz.astype(z.dtype)
        z = conditioned_state(z, cov, (theta - state.theta) / half, du)
    new_state = PolicyState(
        xhat=xhat,
        started=jnp.ones((), bool),
        z=None if z is None else z.astype(z_prev.dtype),
        theta=theta.astype(state.theta.dtype),
        hint=hint,
        sens=None if sens is None else sens.astype(state.sens.dtype),
        cov=None if cov is None else cov.astype(state.cov.dtype),
        noise_scale=None
        if noise_scale is None
        else noise_scale.astype(state.noise_scale.dtype),
        bias=bias,
    )
    return new_state, theta, xhat
