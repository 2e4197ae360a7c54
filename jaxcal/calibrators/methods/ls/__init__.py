"""Sliding-window least squares on the model (Levenberg-Marquardt,
:mod:`jaxcal.calibrators.methods.ls.window`); with hidden states the moving-window fit
of
the parameters and the window's initial state
(:mod:`jaxcal.calibrators.methods.ls.window_state`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig, make_least_squares
from jaxcal.calibrators.methods.ls.window_state import make_window_least_squares
from jaxcal.calibrators.methods.protocol import Method
from jaxcal.calibrators.model_based import (
    fleet_built,
    model_based_factory,
    model_check,
    stream_calibrator,
)
from jaxcal.calibrators.programs import compiled


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


def factory(problem, cfg: LeastSquares, measure=None):
    """``make(inputs) -> Calibrator``: the window fit on ``problem``'s model."""
    return model_based_factory(
        problem, cfg.solver, make_least_squares, _window, measure
    )


def build(problem, cfg: LeastSquares, buckets, seed: int = 0):
    """The window fit's fleet program and a uniform's std over the box."""
    del seed

    def program_of():
        make, check = factory(problem, cfg), model_check(problem)
        return compiled.fleet_program(problem, cfg, make, check, buckets.dtype)

    prior = problem.theta_half_width / np.sqrt(3)
    return fleet_built(problem, cfg, program_of, prior, buckets.dtype)


METHOD = Method(
    name="ls",
    config=LeastSquares,
    build=build,
    make=lambda problem, cfg, buckets=None, seed=0: stream_calibrator(
        problem, cfg, factory
    ),
    check=lambda problem, cfg: model_check(problem),
    factory=factory,
    label="LS",
    white_std=False,  # its online check scales the std to its own errors
)
