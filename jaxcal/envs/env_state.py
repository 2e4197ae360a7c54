"""The tracking environment's state and its interface as pure functions.

Four state classes, one per (model with memory?, incremental actions?), and a fifth
for a Gauss-Newton observation on a model with memory, so that the
checkpoints of each kind keep their layout (:func:`make_env_state` picks one); the
environment itself is :class:`Env`, the gymnax-style ``reset``/``step`` pair built by
:func:`jaxcal.envs.tracking.make_tracking_env`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from flax import struct

from jaxcal.envs.env_config import EnvConfig
from jaxcal.typedefs import Array


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


@struct.dataclass
class SensitiveEnvState(StatefulIncrementEnvState):
    """:class:`StatefulIncrementEnvState` of a Gauss-Newton observation
    (``EnvConfig.gauss_newton``): the state's sensitivity to theta is carried.

    Attributes:
        sens: [Z, P] dz / dtheta
            (:func:`~jaxcal.envs.increment.step_with_sensitivity`).
    """

    sens: Array


@struct.dataclass
class FilteredEnvState(IncrementEnvState):
    """:class:`IncrementEnvState` with the filter step's covariance
    (``EnvConfig.gn_filter``): ``cov`` [P, P] in half-box units
    (:func:`~jaxcal.envs.increment.filter_feature`)."""

    cov: Array


@struct.dataclass
class AdaptiveFilteredEnvState(FilteredEnvState):
    """:class:`FilteredEnvState` of a filter that adapts its noise
    (``EnvConfig.filter_adapt``): ``noise_scale`` [S] each output's noise variance
    over the declared one (:func:`~jaxcal.envs.increment.adapted_noise_scale`)."""

    noise_scale: Array


@struct.dataclass
class FilteredSensitiveEnvState(SensitiveEnvState):
    """:class:`SensitiveEnvState` with the filter step's covariance ``cov``
    [P, P]."""

    cov: Array


@struct.dataclass
class JointFilteredEnvState(FilteredSensitiveEnvState):
    """:class:`FilteredSensitiveEnvState` of the joint filter of a model with memory
    (:mod:`jaxcal.envs.joint_filter`): ``cov`` is ``[Z + P, Z + P]``, ``z`` the state
    the filter corrected and ``fstep`` [P] its theta step (half-box units), which the
    next action is compared with."""

    fstep: Array


def make_env_state(
    unit, time, step, xhat, z, theta=None, sens=None, cov=None, fstep=None,
    noise_scale=None,
) -> EnvState:  # fmt: skip
    """The state of a static model (``z is None``) or of one with memory, with
    theta when the actions are incremental, the state's sensitivity with a
    Gauss-Newton observation and the filter's covariance with its step (each its
    own class, so that the checkpoints of the runs before it keep their layout)."""
    fields = dict(unit=unit, time=time, step=step, xhat=xhat)
    if fstep is not None:
        return JointFilteredEnvState(
            **fields, z=z, theta=theta, sens=sens, cov=cov, fstep=fstep
        )
    if cov is not None:
        if sens is not None:
            return FilteredSensitiveEnvState(
                **fields, z=z, theta=theta, sens=sens, cov=cov
            )
        if noise_scale is not None:
            return AdaptiveFilteredEnvState(
                **fields, theta=theta, cov=cov, noise_scale=noise_scale
            )
        return FilteredEnvState(**fields, theta=theta, cov=cov)
    if sens is not None:
        return SensitiveEnvState(**fields, z=z, theta=theta, sens=sens)
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
