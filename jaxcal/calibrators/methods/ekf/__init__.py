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
from jaxcal.calibrators.methods.on_model import on_model_method


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


METHOD = on_model_method(
    "ekf", EKF, make_ekf, make_joint_ekf, label="EKF",
    prior_std=lambda problem, cfg: cfg.filter.prior_std * problem.theta_half_width,
)  # fmt: skip
