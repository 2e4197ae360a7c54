"""The extended Kalman filter on the model (:mod:`.filter`): the UKF's state-space
model and treatment of missing outputs, linearised by forward mode instead of
propagating sigma points. One model evaluation and ``Z + P`` tangents a sample
against the UKF's ``2 (Z + P) + 1`` evaluations: cheaper on a model whose evaluation
dominates (a Newton solve, many states), as good where the model is close to linear
over the posterior's spread."""

from __future__ import annotations

import dataclasses
from typing import Any

from jaxcal.calibrators.methods.ekf.filter import EKFConfig, make_ekf, make_joint_ekf
from jaxcal.calibrators.methods.protocol import Method
from jaxcal.calibrators.model_based import (
    fleet_built,
    model_based_factory,
    model_check,
    stream_calibrator,
)
from jaxcal.calibrators.programs import compiled


@dataclasses.dataclass(frozen=True)
class EKF:
    """The extended Kalman filter on the model (random-walk parameters); with hidden
    states the joint state-and-parameter filter. ``filter``: its settings (``r`` is
    1: the noise is the ``noise_std`` input); ``state_std`` / ``state_q``: the
    initial state's std and the states' process noise (scalar, per state, or
    ``{state: value}``; default 1 % / 1e-6 of each state's size)."""

    filter: EKFConfig = EKFConfig(r=1.0)
    state_std: Any = None
    state_q: Any = None

    name = "ekf"
    field_type = EKFConfig
    field_name = "filter"


def factory(problem, cfg: EKF, measure=None):
    """``make(inputs) -> Calibrator``: the filter on ``problem``'s model."""
    return model_based_factory(problem, cfg.filter, make_ekf, make_joint_ekf, measure)


def build(problem, cfg: EKF, buckets, seed: int = 0):
    """The filter's fleet program and its prior std, ``prior_std`` of the
    half-width."""
    del seed

    def program_of():
        make, check = factory(problem, cfg), model_check(problem)
        return compiled.fleet_program(problem, cfg, make, check, buckets.dtype)

    prior = cfg.filter.prior_std * problem.theta_half_width
    return fleet_built(problem, cfg, program_of, prior, buckets.dtype)


METHOD = Method(
    name="ekf",
    config=EKF,
    build=build,
    make=lambda problem, cfg, buckets=None, seed=0: stream_calibrator(
        problem, cfg, factory
    ),
    check=lambda problem, cfg: model_check(problem),
    factory=factory,
    label="EKF",
)
