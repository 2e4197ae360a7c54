"""Any model's rows as a training run's data: splits, padding, the problem.

:func:`load_table_data` reads a file of rows named as the model names its variables
(CSV, Parquet, NASA C-MAPSS text; :func:`jaxcal.data.readers.read_dataset`) or takes
a :class:`~jaxcal.data.dataset.Dataset`, and returns the same
:class:`~jaxcal.training.data.calibration.CalibrationData` an N-CMAPSS file gives.

Splits are whole units (one unit is one stream; a window never mixes units):

* a ``split`` column is used as it is: ``train`` / ``val`` / ``test`` rows; without
  ``val`` rows, the validation units are taken from ``train`` (or ``dev``, the
  N-CMAPSS name) as for N-CMAPSS files (``val_units`` or the last ``val_fraction``
  of them);
* without one, ``test_units`` (default: the last ``test_fraction`` of the units, at
  least one) are held out for the final test and ``val_units`` (default: the last
  ``val_fraction`` of the rest, at least one) for validation; at least one training
  unit must remain.

The action box (:func:`box_of`): when the training and validation rows carry the
true value of every declared parameter, their range widened by ``theta_margin`` (the
paper's box, as for the turbofan files: a box as tight as the data gives the policy
the finest action resolution); otherwise the model's bounds.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.data.padded import Padded
from jaxcal.data.readers import read_dataset
from jaxcal.model import Model
from jaxcal.precision import float_dtype
from jaxcal.problem import VARYING_TOLERANCE, labelled_box
from jaxcal.training.data.calibration import CalibrationData, training_problem

SPLITS = ("train", "val", "test", "dev")


def _ids(units) -> list[int]:
    return [int(u) for u in units]


def _last_share(units: list[int], fraction: float) -> list[int]:
    """The last ``fraction`` of ``units``: none at 0, else at least one, never all."""
    num = max(1, round(fraction * len(units))) if fraction else 0
    return units[len(units) - num :] if num < len(units) else []


def hold_out_units(
    units: Sequence[int],
    test_units: Sequence[int] | None,
    val_units: Sequence[int] | None,
    test_fraction: float,
    val_fraction: float,
    source: str,
) -> tuple[list[int], list[int], list[int]]:
    """(train, val, test) unit ids of data without a split column.

    Raises:
        ValueError: an unknown unit id, a unit in two splits, or too few units
            (the message says how many there are and how to choose).
    """
    units = _ids(units)
    for name, chosen in (("test_units", test_units), ("val_units", val_units)):
        stray = sorted(set(_ids(chosen or ())) - set(units))
        if stray:
            raise ValueError(f"{name}={stray}: not units of {source}; units: {units}")
    if test_units is None:
        if len(units) < 3:
            raise ValueError(
                f"{source} has {len(units)} unit(s): holding whole units out for "
                "validation and test needs at least 3 (a unit column with more "
                "units, or a split column)"
            )
        test = units[len(units) - max(1, round(test_fraction * len(units))) :]
    else:
        test = _ids(test_units)
    rest = [u for u in units if u not in test]
    if val_units is None:
        val = _last_share(rest, val_fraction)
    else:
        val = _ids(val_units)
        both = sorted(set(val) & set(test))
        if both:
            raise ValueError(f"units {both} are in both val_units and test_units")
    train = [u for u in rest if u not in val]
    if not test or not train:
        raise ValueError(
            f"{source}: the split leaves train units {train}, test units {test}; "
            f"choose test_units= / val_units= among {units}"
        )
    return train, val, test


def split_by_column(
    data: Dataset, val_units: Sequence[int] | None, val_fraction: float
) -> tuple[list[int], list[int], list[int]]:
    """(train, val, test) unit ids of data with a ``split`` column."""
    labels = sorted(set(data.split.tolist()))
    stray = [s for s in labels if s not in SPLITS]
    if stray:
        raise ValueError(
            f"{data.source}: split column values {stray}; expected {list(SPLITS)}"
        )

    def units_of(split):
        return _ids(data.select_split(split).units) if split in labels else []

    test = units_of("test")
    train, val, dev = units_of("train"), units_of("val"), units_of("dev")
    if val and val_units is not None:
        raise ValueError(
            f"{data.source}: the split column defines the val units {val}; leave "
            "val_units out"
        )
    if not val:  # no val rows: hold validation units out of train, as of dev
        train, dev = [], train + dev
    if dev:
        if val_units is None:
            picked = _last_share(dev, val_fraction)
        else:
            picked = _ids(val_units)
            stray = sorted(set(picked) - set(dev))
            if stray:
                raise ValueError(f"val_units {stray} are not dev units ({dev})")
        train += [u for u in dev if u not in picked]
        val += picked
    if not train or not test:
        raise ValueError(
            f"{data.source}: the split column gives train units {train} and test "
            f"units {test}; both are needed"
        )
    return train, val, test


def pad_units(data: Dataset, units: Sequence[int], theta_names) -> Padded:
    """The rows of ``units`` as :class:`~jaxcal.data.padded.Padded` (current float
    dtype)."""
    padded = data.select_units(units).padded(float_dtype())
    theta = None
    if padded.theta is not None and set(theta_names) <= set(data.theta_names):
        cols = [data.theta_names.index(n) for n in theta_names]
        theta = padded.theta[..., cols]
    return padded._replace(theta=theta, rows=None)  # rows of the selection: not kept


def box_of(
    model: Model, dev: Dataset, theta_names, theta_margin: float, use_labels=True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """``(low [P], high [P], theta_base [P_all], which)`` (see the module docstring;
    ``use_labels=False``: the model's bounds and nominal values, labels are for
    scoring only)."""
    base = model.nominal.copy()
    if use_labels:
        for j, name in enumerate(dev.theta_names):
            base[model.parameter_names.index(name)] = dev.theta[:, j].mean()
        if dev.theta is not None and set(theta_names) <= set(dev.theta_names):
            cols = [dev.theta_names.index(n) for n in theta_names]
            low, high = labelled_box(dev.theta[:, cols], theta_margin)
            return low, high, base, "labelled range"
    idx = model.parameter_index(theta_names)
    low, high = (b[idx] for b in model.bounds)
    which = "model bounds" if use_labels else "model bounds (labels for scoring only)"
    return low, high, base, which


def default_theta(model: Model, dev: Dataset) -> tuple[str, ...]:
    """The labelled parameters that vary over the training rows, else all."""
    if dev.theta is not None:
        spread = dev.theta.max(axis=0) - dev.theta.min(axis=0)
        varying = [
            n
            for n, s in zip(dev.theta_names, spread, strict=True)
            if s > VARYING_TOLERANCE
        ]
        if varying:
            return tuple(n for n in model.parameter_names if n in varying)
    return model.parameter_names


def load_table_data(
    source,
    model: Model,
    *,
    theta: Sequence[str] = (),
    outputs: Sequence[str] = (),
    test_units: Sequence[int] | None = None,
    val_units: Sequence[int] | None = None,
    test_fraction: float = 0.2,
    val_fraction: float = 0.15,
    theta_margin: float = 0.1,
    use_labels: bool = True,
    nonfinite: str = "error",
    rename: dict[str, str] | None = None,
    norm_dtype=np.float64,
) -> CalibrationData:
    """Any model's data file (or Dataset) as :class:`CalibrationData`.

    Args:
        source: a path (``.csv``, ``.parquet``, ``.txt``) or a Dataset.
        model: the model whose variables the columns are named after.
        theta: declared parameters (``()``: :func:`default_theta`).
        outputs: used outputs (``()``: every model output the data have).
        test_units, val_units, test_fraction, val_fraction: the hold-out (module
            docstring).
        theta_margin: widening of a labelled box.
        use_labels: take the box, the fixed parameters' values and the default
            ``theta`` from the labels (``False``: the model's bounds and nominal
            values; the labels only score).
        nonfinite, rename: the reader's (``"error"`` / ``"drop"``; column renames).
        norm_dtype: the dtype the problem's normalisation is computed in (a
            training run's: :func:`jaxcal.training.data.run.run_dtype`).

    Raises:
        ValueError: unreadable data, names that do not match the model, a bad
            split, or units too short for one step (the message says which).
    """
    # a policy trains on complete rows: a partial one is non-finite here as before
    data = read_dataset(
        source, model, rename=rename, nonfinite=nonfinite, partial=False
    )
    data = data.for_model(model, tuple(outputs) or None)
    train, val, test = _split(data, test_units, val_units, test_fraction, val_fraction)
    dev = data.select_units(train + val)
    theta = tuple(theta) or (
        default_theta(model, dev) if use_labels else model.parameter_names
    )
    model.parameter_index(theta)  # unknown names: an error listing the valid ones
    low, high, base, which = box_of(model, dev, theta, theta_margin, use_labels)
    splits = {
        name: pad_units(data, ids, theta) if ids else None
        for name, ids in (("train", train), ("val", val), ("test", test))
    }
    _check_lengths(data.source, splits)
    problem = training_problem(
        model, splits["train"], theta, data.output_names, base, low, high, norm_dtype
    )
    return CalibrationData(
        train=splits["train"],
        val=splits["val"],
        test=splits["test"],
        problem=problem,
        info={
            "path": data.source,
            "box": which,
            "rows": {
                k: int(v.lengths.sum()) for k, v in splits.items() if v is not None
            },
            "units": {"train": train, "val": val, "test": test},
            "dropped": data.dropped,
        },
    )


def _split(data: Dataset, test_units, val_units, test_fraction, val_fraction):
    """(train, val, test) unit ids: by the ``split`` column when the data have one
    (:func:`split_by_column`), else held out (:func:`hold_out_units`).

    Raises:
        ValueError: ``test_units`` given with a split column, or a bad split.
    """
    if data.split is not None:
        if test_units is not None:
            raise ValueError(
                f"{data.source} has a split column: it defines the test units "
                "(leave test_units out, or drop the column)"
            )
        return split_by_column(data, val_units, val_fraction)
    return hold_out_units(
        data.units, test_units, val_units, test_fraction, val_fraction, data.source
    )


def _check_lengths(source, splits: dict) -> None:
    """Every unit must have 2 rows at least (one step).

    Raises:
        ValueError: naming the shorter units.
    """
    short = [
        int(u)
        for units in splits.values()
        if units is not None
        for u, n in zip(units.unit_ids, units.lengths, strict=True)
        if n < 2
    ]
    if short:
        raise ValueError(f"{source}: unit(s) {short} have fewer than 2 rows")
