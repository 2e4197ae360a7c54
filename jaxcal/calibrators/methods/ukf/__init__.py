"""The unscented Kalman filter on the model (:mod:`jaxcal.calibrators.ukf`): the
paper's baseline, random-walk parameters; with hidden states the joint
state-and-parameter filter. Its compiled program also returns the innovations: the
screening passes and the method's own run share it
(:mod:`jaxcal.calibrators.front.screen`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from jaxcal.calibrators.methods.protocol import Method
from jaxcal.calibrators.model_based import (
    fleet_built,
    model_based_factory,
    model_check,
    stream_calibrator,
)
from jaxcal.calibrators.programs import compiled
from jaxcal.calibrators.ukf import UKFConfig, make_joint_ukf, make_ukf


@dataclasses.dataclass(frozen=True)
class UKF:
    """The unscented Kalman filter on the model (random-walk parameters); with hidden
    states the joint state-and-parameter filter. ``filter``: its settings (``r`` is
    1: the noise is the ``noise_std`` input); ``state_std`` / ``state_q``: the
    initial state's std and the states' process noise (scalar, per state, or
    ``{state: value}``; default 1 % / 1e-6 of each state's size)."""

    filter: UKFConfig = UKFConfig(r=1.0)
    state_std: Any = None
    state_q: Any = None

    name = "ukf"
    field_type = UKFConfig
    field_name = "filter"


def factory(problem, cfg: UKF, measure=None):
    """``make(inputs) -> Calibrator``: the filter on ``problem``'s model."""
    return model_based_factory(problem, cfg.filter, make_ukf, make_joint_ukf, measure)


def ukf_program(problem, cfg: UKF, dtype):
    """The UKF's compiled program with innovations (:func:`compiled.filter_program`):
    the screening passes and the method's own run share it."""
    make = factory(problem, cfg)
    return compiled.filter_program(problem, cfg, make, model_check(problem), dtype)


def build(problem, cfg: UKF, buckets, seed: int = 0):
    """The filter's fleet program (the screening's, its innovations dropped) and
    its prior std, ``prior_std`` of the half-width."""
    del seed

    def program_of():
        filt = ukf_program(problem, cfg, buckets.dtype)

        def program(inputs, w, x, mask):  # nothing to probe: the screen's program
            import jax.numpy as jnp

            return filt(inputs, w, x, mask, jnp.zeros_like(mask))[0]

        return program

    prior = cfg.filter.prior_std * problem.theta_half_width
    return fleet_built(problem, cfg, program_of, prior, buckets.dtype)


METHOD = Method(
    name="ukf",
    config=UKF,
    build=build,
    make=lambda problem, cfg, buckets=None, seed=0: stream_calibrator(
        problem, cfg, factory
    ),
    check=lambda problem, cfg: model_check(problem),
    screening=lambda cfg: cfg,
    factory=factory,
    label="UKF",
)
