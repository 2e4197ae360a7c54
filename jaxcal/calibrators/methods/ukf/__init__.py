"""The unscented Kalman filter on the model (:mod:`jaxcal.calibrators.ukf`): the
paper's baseline, random-walk parameters; with hidden states the joint
state-and-parameter filter. Its compiled program also returns the innovations: the
screening passes and the method's own run share it
(:mod:`jaxcal.calibrators.front.screen`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax.numpy as jnp

from jaxcal.calibrators.methods.on_model import model_check, on_model_method
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


def _without_probe(problem, cfg, make, check, dtype):
    """The fleet program: the screening's (:func:`ukf_program`), nothing probed and
    its innovations dropped."""
    filt = compiled.filter_program(problem, cfg, make, check, dtype)

    def program(inputs, w, x, mask):
        return filt(inputs, w, x, mask, jnp.zeros_like(mask))[0]

    return program


METHOD = on_model_method(
    "ukf", UKF, make_ukf, make_joint_ukf, label="UKF",
    prior_std=lambda problem, cfg: cfg.filter.prior_std * problem.theta_half_width,
    program=_without_probe, screening=lambda cfg: cfg,
)  # fmt: skip


def ukf_program(problem, cfg: UKF, dtype):
    """The UKF's compiled program with innovations (:func:`compiled.filter_program`):
    the screening passes and the method's own run share it."""
    make = METHOD.factory(problem, cfg)
    return compiled.filter_program(problem, cfg, make, model_check(problem), dtype)
