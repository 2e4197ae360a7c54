"""A trained tracking policy as a :class:`~jaxcal.calibrators.interface.Calibrator`.

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
without one. Only a single stream does (deployment, one sample per call): batched over
units, the hinted solve's ``lax.cond`` fall-back runs for every unit, so whole
trajectories and fleets keep the cold solve (and the paper's bits).

Everything the step reads is a leaf of :class:`PolicyParams`, so one jitted runner
(:func:`make_fleet_runner`) serves any trained policy of the same architecture
without retracing.

Guarded samples (:mod:`jaxcal.calibrators.interface`): the runners take a
:class:`~jaxcal.calibrators.interface.SampleCheck`; :func:`range_check` builds it from
the run's training range (``Problem.input_range``) widened by
:data:`TRAINING_RANGE_MARGIN` of its span on each side. A sample outside it is
flagged and skipped, never clipped into the action box.
"""

from __future__ import annotations

from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from jaxcal.calibrators.interface import (
    Calibrator,
    CalOutput,
    CalStepOutput,
    GuardCarry,
    SampleCheck,
    guarded_update,
    initial_carry,
    run_fleet,
    sample_reason,
)
from jaxcal.calibrators.uncertainty import ThetaBand, band_std
from jaxcal.envs.increment import apply_increment, increment_observation
from jaxcal.envs.memory import HintedDynamics, StatefulDynamics, as_stateful
from jaxcal.envs.tracking import Dynamics, EnvParams, action_to_theta
from jaxcal.typedefs import Array, PRNGKey, PyTree

# "Far outside the training range": beyond the training min/max by more than this
# fraction of its span. Test units drift past the training range as they degrade;
# half a span is far beyond any such drift and far inside a unit or sign error.
TRAINING_RANGE_MARGIN = 0.5


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
class IncrementPolicyParams(PolicyParams):
    """:class:`PolicyParams` of a policy with incremental actions (its own class, so
    that checkpoints of absolute-action policies keep their layout).

    Attributes:
        step_ref: ``[P]`` residual RMS at which a step is half its largest.
        max_increment: largest step as a share of the box width (static).
    """

    step_ref: Array
    max_increment: float = struct.field(pytree_node=False, default=0.5)


@struct.dataclass
class StartedIncrementPolicyParams(IncrementPolicyParams):
    """:class:`IncrementPolicyParams` of a policy that starts a stream at a given
    theta rather than the box centre (its own class: the checkpoints of the runs
    before it keep their layout).

    Attributes:
        theta_start: ``[P]`` theta before a stream's first sample.
    """

    theta_start: Array | None = None


@struct.dataclass
class PolicyState:
    """Calibrator state: the model output (and state) of the previous sample.

    Attributes:
        xhat: ``[S]`` x-hat_{t-1} (physical units).
        started: ``[]`` bool, False before the first sample.
        z: ``[Z]`` model state after the previous sample; ``None``: static model.
    """

    xhat: Array
    started: Array
    z: Array | None = None
    theta: Array | None = None  # [P] theta_{t-1} (incremental actions)
    count: Array | None = None  # [] int32 samples taken (with an uncertainty band)
    hint: PyTree | None = None  # the model's solver warm start (HintedDynamics)


def policy_params_from_env(
    env_params: EnvParams,
    actor_params: PyTree,
    *,
    max_increment: float | None = None,
    theta_start: Array | None = None,
) -> PolicyParams:
    """The deployment parameters of a policy trained on ``env_params``
    (``max_increment``: the env's, for incremental actions; ``theta_start``: where
    an incremental policy starts, ``None``: the box centre)."""
    fields = dict(
        actor=actor_params,
        dyn_params=env_params.dyn_params,
        w_mean=env_params.w_mean,
        w_std=env_params.w_std,
        x_mean=env_params.x_mean,
        x_std=env_params.x_std,
        theta_low=env_params.theta_low,
        theta_high=env_params.theta_high,
    )
    if env_params.step_ref is None:
        return PolicyParams(**fields)
    if max_increment is None:
        raise ValueError("an incremental policy needs the env's max_increment")
    fields.update(step_ref=env_params.step_ref, max_increment=max_increment)
    if theta_start is None:
        return IncrementPolicyParams(**fields)
    start = jnp.asarray(theta_start, env_params.theta_low.dtype)
    return StartedIncrementPolicyParams(**fields, theta_start=start)


def make_policy_calibrator(
    actor: nn.Module,
    dynamics: Dynamics | StatefulDynamics,
    params: PolicyParams,
    band: ThetaBand | None = None,
    *,
    warm_start: bool = False,
) -> Calibrator:
    """The deterministic policy pi* and the dynamics as ``Calibrator(init, step)``.

    Args:
        actor: the agent's actor module (``apply(params, obs) -> (mean, log_std)``).
        dynamics: ``dynamics(dyn_params, w [W], xhat [S], theta [P]) -> xhat [S]``,
            or a :class:`~jaxcal.envs.memory.StatefulDynamics`.
        params: :class:`PolicyParams` (may be traced).
        band: the run's calibrated error band
            (:mod:`jaxcal.calibrators.uncertainty`, fitted on its validation units);
            ``None``: no uncertainty.
        warm_start: carry the model's solver hint from sample to sample (a
            :class:`~jaxcal.envs.memory.HintedDynamics`; ignored otherwise). For one
            stream, one sample per call: under ``vmap`` the hinted solve's fall-back
            runs for every unit and costs more than the cold solve.

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
    hinted = warm_start and isinstance(dynamics, HintedDynamics)

    def transition(state: PolicyState, z, w_t, xhat_prev, theta):
        """(z, x-hat, hint) of one model step, warm-started when the model can."""
        if not hinted:
            return (*dyn.step(params.dyn_params, z, w_t, xhat_prev, theta), None)
        hint, xhat = dynamics.step(params.dyn_params, state.hint, w_t, xhat_prev, theta)
        return z, xhat, hint

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> PolicyState:
        del key  # deterministic; x-hat starts at the first measurement
        z0 = dyn.init(params.dyn_params, w0.astype(x0.dtype))
        z0 = None if z0 is None else z0.astype(x0.dtype)
        theta0 = None
        if incremental:  # the run's start, else the box centre (the env's reset_at)
            theta0 = getattr(params, "theta_start", None)
            if theta0 is None:
                theta0 = 0.5 * (params.theta_low + params.theta_high)
        count = None if band is None else jnp.zeros((), jnp.int32)
        hint = dynamics.init_hint() if hinted else None
        return PolicyState(
            xhat=x0, started=jnp.zeros((), bool), z=z0, theta=theta0, count=count,
            hint=hint,
        )  # fmt: skip

    def or_first_state(state: PolicyState, z: Array | None, w_t: Array, x_t: Array):
        # before any sample the model state is init(w_0) (the env's z_ref[0])
        if not dyn.num_states:
            return z
        z_first = dyn.init(params.dyn_params, w_t.astype(x_t.dtype))
        return jnp.where(state.started, z, z_first.astype(z.dtype))

    def absolute_step(state: PolicyState, w_t: Array, x_t: Array):
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
        z = or_first_state(state, z, w_t, x_t)  # the first sample's: init
        new_state = PolicyState(xhat=xhat, started=jnp.ones((), bool), z=z, hint=hint)
        return new_state, theta, xhat

    def increment_step(state: PolicyState, w_t: Array, x_t: Array):
        # predict sample t with theta_{t-1}, then correct theta on its error
        xhat_prev = jnp.where(state.started, state.xhat, x_t)
        z_prev = or_first_state(state, state.z, w_t, x_t)
        z, xhat, hint = transition(state, z_prev, w_t, xhat_prev, state.theta)
        xhat = xhat.astype(x_t.dtype)
        resid = (x_t - xhat) / params.x_std
        obs = increment_observation(
            resid,
            (w_t - params.w_mean) / params.w_std,
            state.theta,
            params.theta_low,
            params.theta_high,
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
        new_state = PolicyState(
            xhat=xhat,
            started=jnp.ones((), bool),
            z=None if z is None else z.astype(z_prev.dtype),
            theta=theta.astype(state.theta.dtype),
            hint=hint,
        )
        return new_state, theta, xhat

    def step(
        state: PolicyState, w_t: Array, x_t: Array
    ) -> tuple[PolicyState, CalStepOutput]:
        run = increment_step if incremental else absolute_step
        new_state, theta, xhat = run(state, w_t, x_t)
        if band is None:
            return new_state, CalStepOutput(theta=theta, xhat=xhat)
        aux = {"theta_std": band_std(band, state.count).astype(theta.dtype)}
        new_state = new_state.replace(count=state.count + 1)
        return new_state, CalStepOutput(theta=theta, xhat=xhat, aux=aux)

    return Calibrator(init, step)


def range_check(problem, margin: float = TRAINING_RANGE_MARGIN) -> SampleCheck | None:
    """The valid input box of a run: its training range widened by ``margin``.

    Args:
        problem: the run's :class:`~jaxcal.problem.Problem` (its ``input_range``:
            min / max of the training units' valid samples).
        margin: fraction of the span added on each side.

    Returns:
        :class:`SampleCheck`, or ``None`` when no range is stored (a run written
        before it was): those check finiteness only.
    """
    rng = getattr(problem, "input_range", None)
    if rng is None:
        return None
    return SampleCheck.from_range(
        rng.w_low, rng.w_high, rng.x_low, rng.x_high, margin=margin
    )


def make_fleet_runner(
    actor: nn.Module, dynamics: Dynamics, *, unroll: int = 1
) -> Callable[..., CalOutput]:
    """A jitted ``run(params, w [U,T,W], x [U,T,S], mask [U,T], check=None,
    band=None)``.

    ``lax.scan`` over time, ``vmap`` over units
    (:func:`~jaxcal.calibrators.interface.run_fleet`); compiled once per array shape
    (and once more with a ``check``). Returns a ``CalOutput`` with ``valid`` and
    ``reason`` per sample.
    """

    def run(
        params: PolicyParams,
        w: Array,
        x: Array,
        mask: Array,
        check: SampleCheck | None = None,
        band: ThetaBand | None = None,
    ) -> CalOutput:
        calibrator = make_policy_calibrator(actor, dynamics, params, band)
        return run_fleet(calibrator, w, x, mask, unroll=unroll, check=check)

    return jax.jit(run)


def make_stream_step(
    actor: nn.Module, dynamics: Dynamics
) -> Callable[[PolicyParams, PolicyState, Array, Array], tuple[PolicyState, Array]]:
    """A jitted single-sample step ``(params, state, w [W], x [S]) -> (state, theta)``.

    The raw step, unguarded (the CPU bench's reference); deployment uses
    :func:`make_guarded_stream_step`.
    """

    def step(params: PolicyParams, state: PolicyState, w: Array, x: Array):
        new_state, out = make_policy_calibrator(actor, dynamics, params).step(
            state, w, x
        )
        return new_state, out.theta

    return jax.jit(step)


def initial_guard_carry(
    actor: nn.Module,
    dynamics: Dynamics,
    params: PolicyParams,
    band: ThetaBand | None = None,
    *,
    warm_start: bool = False,
) -> GuardCarry:
    """The carry of a guarded stream before its first sample.

    Before any ok sample the outputs are zeros (theta = 0: healthy modifiers, as
    ``run_calibrator`` outputs on leading padding) and the step, if fed a flagged
    first sample, sees zeros (its result is discarded). ``warm_start``: as
    :func:`make_policy_calibrator` (the carry then holds the model's first hint).
    """
    w = jnp.zeros_like(params.w_mean)
    x = jnp.zeros_like(params.x_mean)
    num_states = as_stateful(dynamics).num_states
    z = jnp.zeros((num_states,), x.dtype) if num_states else None
    theta = None
    if isinstance(params, IncrementPolicyParams):
        theta = 0.5 * (params.theta_low + params.theta_high)
    count = None if band is None else jnp.zeros((), jnp.int32)
    hinted = warm_start and isinstance(dynamics, HintedDynamics)
    hint = dynamics.init_hint() if hinted else None
    state = PolicyState(
        xhat=x, started=jnp.zeros((), bool), z=z, theta=theta, count=count, hint=hint
    )
    step = make_policy_calibrator(
        actor, dynamics, params, band, warm_start=warm_start
    ).step
    return initial_carry(step, state, w, x)


def make_guarded_stream_step(
    actor: nn.Module, dynamics: Dynamics, *, warm_start: bool = False
) -> Callable[..., tuple[GuardCarry, CalStepOutput, Array]]:
    """A jitted guarded step ``(params, carry, w [W], x [S], check, band=None) ->
    (carry, out, reason [])``: the rule of ``run_calibrator`` for one sample
    (:func:`~jaxcal.calibrators.interface.guarded_update`). ``check`` may be ``None``;
    ``warm_start``: as :func:`make_policy_calibrator` (with its carry from
    :func:`initial_guard_carry`).
    """

    def step(params, carry: GuardCarry, w: Array, x: Array, check, band=None):
        calibrator = make_policy_calibrator(
            actor, dynamics, params, band, warm_start=warm_start
        )
        reason = sample_reason(check, w, x)
        return guarded_update(calibrator.step, carry, w, x, reason)

    return jax.jit(step)
