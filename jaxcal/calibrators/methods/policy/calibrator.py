"""A trained tracking policy as a :class:`~jaxcal.calibrators.interface.Calibrator`,
and its jitted runners.

The calibrator, the paper's deployment step (§3.1), is :func:`make_policy_calibrator`
(:mod:`jaxcal.calibrators.methods.policy.step`, where its equations are); what it reads
and carries, :class:`PolicyParams` and :class:`PolicyState`, is in
:mod:`jaxcal.calibrators.methods.policy.params`. Both are re-exported here, the one
import path. This module runs it: over a fleet (:func:`make_fleet_runner`), one sample
per call (:func:`make_stream_step`), or one guarded sample per call
(:func:`make_guarded_stream_step` from :func:`initial_guard_carry`).

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

from jaxcal.calibrators.interface import (
    CalOutput,
    CalStepOutput,
    GuardCarry,
    SampleCheck,
    guarded_update,
    initial_carry,
    run_fleet,
    sample_reason,
)
from jaxcal.calibrators.methods.policy.params import (  # noqa: F401 (re-exported: one import path)
    IncrementPolicyParams,
    PolicyParams,
    PolicyState,
    StartedIncrementPolicyParams,
    filter_settings,
    policy_params_from_env,
    with_output_states,
)
from jaxcal.calibrators.methods.policy.step import (
    fresh_state,
    make_policy_calibrator,
    start_theta,
)
from jaxcal.calibrators.uncertainty.conformal import ThetaBand
from jaxcal.envs.memory import HintedDynamics, as_stateful
from jaxcal.envs.tracking import Dynamics
from jaxcal.typedefs import Array

# "Far outside the training range": beyond the training min/max by more than this
# fraction of its span. Test units drift past the training range as they degrade;
# half a span is far beyond any such drift and far inside a unit or sign error.
TRAINING_RANGE_MARGIN = 0.5


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
    ``reason`` per sample. A model with a warm-started solve (the turbofan's) carries
    it along each unit, as a stream does: the theta of streaming the unit's rows
    one by one (to 1e-12), at a fraction of the cold solve's cost
    (``results/bench/stream_profile.md``).
    """

    def run(
        params: PolicyParams,
        w: Array,
        x: Array,
        mask: Array,
        check: SampleCheck | None = None,
        band: ThetaBand | None = None,
    ) -> CalOutput:
        # run_fleet's init is given each unit's first ok row
        calibrator = make_policy_calibrator(
            actor, dynamics, params, band, start_at_first_sample=False, warm_start=True
        )
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

    Before any ok sample the stream reports the theta it starts from
    (:func:`stream_start_theta`: inside the box, so a stream never reports a value
    the model cannot take and does not jump at its first valid sample); the step, if
    fed a flagged first sample, sees zeros (its result is discarded). ``warm_start``:
    as :func:`make_policy_calibrator` (the carry then holds the model's first hint).
    """
    w = jnp.zeros_like(params.w_mean)
    x = jnp.zeros_like(params.x_mean)
    num_states = as_stateful(dynamics).num_states
    z = jnp.zeros((num_states,), x.dtype) if num_states else None
    hinted = warm_start and isinstance(dynamics, HintedDynamics)
    hint = dynamics.init_hint() if hinted else None
    state = fresh_state(params, band, num_states, x, z, hint)
    step = make_policy_calibrator(
        actor, dynamics, params, band, warm_start=warm_start
    ).step
    carry = initial_carry(step, state, w, x)
    theta0 = stream_start_theta(params).astype(carry.out.theta.dtype)
    return carry._replace(out=carry.out._replace(theta=theta0))


def stream_start_theta(params: PolicyParams) -> Array:
    """``[P]`` what a stream reports before its first valid sample: an incremental
    policy's start (:func:`start_theta`: the run's prior or the box centre); an
    absolute policy's healthy zeros where the box holds them (the turbofan's
    modifiers), else the box centre."""
    theta0 = start_theta(params)
    if theta0 is not None:
        return theta0
    low, high = params.theta_low, params.theta_high
    inside = jnp.all((low <= 0) & (0 <= high))
    return jnp.where(inside, jnp.zeros_like(low), 0.5 * (low + high))


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
