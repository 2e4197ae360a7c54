"""The calibration data set of a training run: padded ``[U, T, ...]`` arrays per split
and the one :class:`~jaxcal.problem.Problem` they define.

:class:`CalibrationData` is what training, evaluation and the paper's comparison read:
the train / validation / test units as :class:`UnitArrays` and the problem (model,
declared parameters, used outputs, action box, normalisation over the training units,
training input range), which :func:`training_problem` derives from the training
units. Its sources, an N-CMAPSS file (:mod:`jaxcal.training.data`, which re-exports
these names) and any model's rows (:mod:`jaxcal.training.tables`), fill it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxcal.model import Model
from jaxcal.problem import InputRange, Normalisation, Problem


class UnitArrays(NamedTuple):
    """One split, padded (host numpy).

    Attributes:
        w: ``[U, T, W]`` operating conditions (ft, -, %, degR).
        x: ``[U, T, S]`` sensors in file units.
        theta: ``[U, T, P]`` declared parameters (labels, for scoring only), or
            ``None`` when the data carry no true values.
        lengths: ``[U]`` int32 valid rows per unit.
        unit_ids: ``[U]`` int64 unit ids of the file.
    """

    w: np.ndarray
    x: np.ndarray
    theta: np.ndarray | None
    lengths: np.ndarray
    unit_ids: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """``[U, T]`` bool, True on valid rows."""
        return np.arange(self.x.shape[1])[None, :] < self.lengths[:, None]

    @property
    def num_samples(self) -> int:
        """Number of valid rows over all units."""
        return int(self.lengths.sum())


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

    train: UnitArrays
    val: UnitArrays | None
    test: UnitArrays
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
    train: UnitArrays,
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
