"""What a deployed policy reads and carries.

:class:`PolicyParams` (and its incremental variants :class:`IncrementPolicyParams`,
:class:`StartedIncrementPolicyParams`) holds everything the step of
:mod:`jaxcal.calibrators.methods.policy.step` reads, every array a leaf (traced,
checkpointable), so one jitted runner serves any trained policy of the same
architecture without retracing; :class:`PolicyState` is what the step carries from
sample to sample. :func:`policy_params_from_env` builds the parameters of a policy
from its training environment's. :mod:`jaxcal.calibrators.methods.policy.calibrator`
re-exports them.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from flax import struct

from jaxcal.envs.increment import FILTER_PRIOR_STD, FILTER_Q
from jaxcal.envs.tracking import EnvParams
from jaxcal.typedefs import Array, PyTree


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
        gauss_newton: the observation holds the residual's Gauss-Newton step
            (static; :class:`~jaxcal.envs.env_config.EnvConfig`).
        gn_filter: it holds the filter's step (static; ``EnvConfig.gn_filter``).
        x_noise: ``[S]`` the measurement noise std the filter weighs the outputs
            by; ``None`` without ``gn_filter`` (the checkpoints before it).
        filter_q: the filter's random walk per sample, half-widths of the box
            (static; ``EnvConfig.filter_q``); ``filter_whole``: its feature is the
            whole step (static; ``EnvConfig.filter_whole``); ``filter_prior_std``:
            its prior std, half-widths of the box (static); ``filter_adapt``:
            the samples the filter on theta alone averages its noise over
            (static; ``EnvConfig.filter_adapt``, 0: the declared noise).
    """

    step_ref: Array
    max_increment: float = struct.field(pytree_node=False, default=0.5)
    gauss_newton: bool = struct.field(pytree_node=False, default=False)
    gn_filter: bool = struct.field(pytree_node=False, default=False)
    x_noise: Array | None = None
    filter_q: float = struct.field(pytree_node=False, default=FILTER_Q)
    filter_whole: bool = struct.field(pytree_node=False, default=False)
    filter_prior_std: float = struct.field(pytree_node=False, default=FILTER_PRIOR_STD)
    filter_adapt: int = struct.field(pytree_node=False, default=0)


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
class OutputStatesPolicyParams(StartedIncrementPolicyParams):
    """:class:`StartedIncrementPolicyParams` of a policy whose filter carries
    output states (:mod:`jaxcal.envs.bias_states`, fitted by the tuning; its own
    class: the checkpoints of the runs before it keep their layout).

    Attributes:
        filter_bias_var: ``[S]`` the random walk per sample of each output's bias,
            (noise stds)^2 (``tune.bias``).
    """

    filter_bias_var: Array | None = None


def with_output_states(params: PolicyParams, bias_var: Array):
    """``params`` (an incremental policy's) with its filter's output-bias states,
    their walk ``bias_var`` (a start theta of ``None``: the box centre, as the
    class it came from)."""
    if hasattr(params, "filter_bias_var"):
        return params.replace(filter_bias_var=bias_var)
    fields = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    fields.setdefault("theta_start", None)
    return OutputStatesPolicyParams(**fields, filter_bias_var=bias_var)


def counts(params: PolicyParams, band) -> bool:
    """Whether a policy's state counts its samples: for its band's time buckets, or
    for the stream's age its Gauss-Newton observation holds."""
    return band is not None or uses_jacobian(params)


def has_bias_states(params: PolicyParams) -> bool:
    """Whether the policy's filter carries output-bias states (a tuned policy with
    ``filter_bias_var``; :mod:`jaxcal.envs.bias_states`)."""
    return getattr(params, "gn_filter", False) and (
        getattr(params, "filter_bias_var", None) is not None
    )


def uses_jacobian(params: PolicyParams) -> bool:
    """Whether the policy observes a step through the model's Jacobian (the
    one-sample Gauss-Newton step or the filter's)."""
    return getattr(params, "gauss_newton", False) or getattr(params, "gn_filter", False)


def initial_sensitivity(params: PolicyParams, num_states: int, dtype) -> Array | None:
    """A stream's first ``dz / dtheta``: zeros ``[Z, P]`` for a Gauss-Newton
    observation on a model with memory
    (:func:`~jaxcal.envs.increment.step_with_sensitivity`), else ``None``."""
    if not (uses_jacobian(params) and num_states):
        return None
    return jnp.zeros((num_states, params.theta_low.shape[-1]), dtype)


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
    # [Z, P] the state's sensitivity to theta (gauss_newton on a model with memory)
    sens: Array | None = None
    cov: Array | None = None  # [P, P] the filter step's covariance (gn_filter)
    # [2, P] Brown's smoothed theta levels: the drift rate a relative band reads
    # (jaxcal.calibrators.uncertainty.lag_scale)
    trend: Array | None = None
    # [S] the adaptive filter's noise variance over the declared one (filter_adapt)
    noise_scale: Array | None = None
    # [S] the filter's output biases in noise stds (filter_bias_var)
    bias: Array | None = None


def filter_settings(env_cfg) -> dict:
    """The static observation and filter fields of :class:`IncrementPolicyParams`
    from the :class:`~jaxcal.envs.env_config.EnvConfig` a policy was trained in
    (the one mapping: the scoring during training and the loaded run both use it)."""
    return dict(
        gauss_newton=env_cfg.gauss_newton,
        gn_filter=env_cfg.gn_filter,
        filter_q=env_cfg.filter_q,
        filter_whole=env_cfg.filter_whole,
        filter_prior_std=env_cfg.filter_prior_std,
        filter_adapt=env_cfg.filter_adapt,
    )


def policy_params_from_env(
    env_params: EnvParams,
    actor_params: PyTree,
    *,
    max_increment: float | None = None,
    theta_start: Array | None = None,
    gauss_newton: bool = False,
    gn_filter: bool = False,
    filter_q: float = FILTER_Q,
    filter_whole: bool = False,
    filter_prior_std: float = FILTER_PRIOR_STD,
    filter_adapt: int = 0,
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
    fields.update(
        step_ref=env_params.step_ref,
        max_increment=max_increment,
        gauss_newton=gauss_newton,
        gn_filter=gn_filter,
        x_noise=env_params.x_noise if gn_filter else None,
        filter_q=filter_q,
        filter_whole=filter_whole,
        filter_prior_std=filter_prior_std,
        filter_adapt=filter_adapt,
    )
    if theta_start is None:
        return IncrementPolicyParams(**fields)
    start = jnp.asarray(theta_start, env_params.theta_low.dtype)
    return StartedIncrementPolicyParams(**fields, theta_start=start)
