"""Sliding-window least squares on the model (Levenberg-Marquardt,
:mod:`jaxcal.calibrators.methods.ls.window`); with hidden states the moving-window fit
of the parameters and the window's initial state
(:mod:`jaxcal.calibrators.methods.ls.window_state`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig, make_least_squares
from jaxcal.calibrators.methods.ls.window_state import make_window_least_squares
from jaxcal.calibrators.methods.on_model import on_model_method


@dataclasses.dataclass(frozen=True)
class LeastSquares:
    """Sliding-window least squares on the model (Levenberg-Marquardt); with hidden
    states the moving-window fit of the parameters and the window's initial state.
    ``solver``: its settings (``r`` is 1); ``state_std``: the window start's std."""

    solver: LeastSquaresConfig = LeastSquaresConfig(r=1.0)
    state_std: Any = None

    name = "ls"
    field_type = LeastSquaresConfig
    field_name = "solver"
    may_be_none = ("prior_std",)  # no prior: the window's data alone
    state_std_floor = 1e-9  # of each state's size: a window start is never exact


def _window(tr, settings, measurement, *, state_q, **common):
    """The moving-window fit of a model with memory (no process noise: ``state_q``
    is the UKF's); a window without excitation must not run off, so a prior is
    always kept."""
    del state_q
    if settings.prior_std is None:
        settings = dataclasses.replace(settings, prior_std=1.0)
    return make_window_least_squares(tr, settings, measurement, **common)


METHOD = on_model_method(
    "ls", LeastSquares, make_least_squares, _window, label="LS",
    prior_std=lambda problem, cfg: problem.theta_half_width / np.sqrt(3),
    white_std=False,  # its online check scales the std to its own errors
)  # fmt: skip
