"""The calibration data set of a training run: padded ``[U, T, ...]`` arrays per split
and the one :class:`~jaxcal.problem.Problem` they define.

:class:`CalibrationData` is what training, evaluation and the paper's comparison read:
the train / validation / test units as :class:`~jaxcal.data.padded.Padded` (the one
padded container) and the problem (model, declared parameters, used outputs, action
box, normalisation over the training units, training input range), which
:func:`training_problem` derives from the training units. Its sources, an N-CMAPSS
file (:mod:`jaxcal.training.data`, which re-exports these names) and any model's rows
(:mod:`jaxcal.training.tables`), fill it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxcal.data.padded import Padded
from jaxcal.model import Model
from jaxcal.problem import InputRange, Normalisation, Problem


class CalibrationData(NamedTuple):
    """Everything a run needs from its data.

    Attributes:
        train, val, test: the splits; ``val`` is ``None`` when no unit is held out.
        problem: the :class:`~jaxcal.problem.Problem`: model, declared parameters
            (``theta_names``, action box ``theta_low``/``theta_high``, the other
            parameters' values ``theta_base``), used outputs, normalisation and
            input range of the training units.
        info: provenance (path, sample rate, rows and units per split).
    """

    train: Padded
    val: Padded | None
    test: Padded
    problem: Problem
    info: dict

    # Read-only views of the problem, for readers written against the older fields.
    @property
    def sensors(self) -> tuple[str, ...]:
        return self.problem.output_names

    @property
    def theta_names(self) -> tuple[str, ...]:
        return self.problem.theta_names

    @property
    def theta_low(self) -> np.ndarray:
        return self.problem.theta_low

    @property
    def theta_high(self) -> np.ndarray:
        return self.problem.theta_high

    @property
    def theta_base(self) -> np.ndarray:
        return self.problem.theta_base

    @property
    def engine(self) -> str:
        """The model's name (the engine configuration for the turbofan)."""
        return self.problem.model.name


def training_problem(
    model: Model,
    train: Padded,
    theta_names, output_names, theta_base, theta_low, theta_high,
) -> Problem:  # fmt: skip
    """The problem of a run: normalisation and input range over the valid rows of
    the training units (float64; the pipeline re-derives the normalisation in the
    run's dtype), noise provisional (1 % of each output's spread; the policy does
    not use it)."""
    rows = np.asarray(train.mask, bool)
    w = np.asarray(train.w, np.float64)[rows]
    x = np.asarray(train.x, np.float64)[rows]
    norm = Normalisation.of(w, x)
    return Problem(
        model=model,
        theta_names=tuple(theta_names),
        output_names=tuple(output_names),
        theta_base=np.asarray(theta_base, np.float64),
        theta_low=np.asarray(theta_low, np.float64),
        theta_high=np.asarray(theta_high, np.float64),
        norm=norm,
        noise_std=0.01 * norm.x_std,
        input_range=InputRange(w.min(0), w.max(0), x.min(0), x.max(0)),
        noise_source="provisional (1 % of each output's spread)",
    )
