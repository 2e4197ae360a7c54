"""The one data container of calibration: :class:`Dataset`, rows in, padded units out.

A data set is a table of ``N`` rows: operating conditions ``w [N, W]`` and outputs
``x [N, S]`` named as the model names them, a unit (trajectory) id, a time or cycle
index, optional true parameters (for scoring) and an optional split label. Every
source becomes one (:mod:`jaxcal.data.readers`: CSV, Parquet, a DataFrame, numpy
arrays, N-CMAPSS HDF5, NASA C-MAPSS text), and every consumer — the calibrators
through :func:`jaxcal.calibrate`, training, evaluation, the diagnosis — reads it.

Calibration runs each unit as its own stream: :meth:`Dataset.padded` turns the rows
into ``[U, T, ...]`` arrays with a validity mask (units padded to the longest) and
remembers each padded cell's original row, so results come back in the input's row
order (:meth:`jaxcal.data.padded.Padded.to_rows`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from jaxcal.data.padded import Padded
from jaxcal.model import Model, names_to_index

# Conditions this close outside the model's range (share of its width) are logging
# jitter around a bound, clipped onto it (and said so) rather than flagged.
JITTER_FRACTION = 0.01


def _float_matrix(name: str, value, num_rows: int | None, names) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != len(names):
        raise ValueError(
            f"Dataset.{name} must be [N, {len(names)}] (columns {list(names)}), got "
            f"shape {arr.shape}"
        )
    if num_rows is not None and arr.shape[0] != num_rows:
        raise ValueError(f"Dataset.{name} has {arr.shape[0]} rows, expected {num_rows}")
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class Dataset:
    """``N`` rows of (conditions, outputs), grouped into units and ordered in time.

    Attributes:
        w: ``[N, W]`` conditions, columns ``condition_names``.
        x: ``[N, S]`` outputs, columns ``output_names``.
        condition_names, output_names: column names (the model's vocabulary).
        unit: ``[N]`` int64 unit id (one stream per unit).
        time: ``[N]`` float64 time or cycle index (rows of a unit are in this order).
        theta: ``[N, P]`` true parameters (``theta_names``) or ``None``.
        split: ``[N]`` str split label (``train``/``val``/``test``/``dev``) or None.
        row: ``[N]`` int64 position of each row in the source (result row order).
        source: provenance (file path or "DataFrame"/"arrays").
        dropped: ``{column: rows}`` dropped by the reader for non-finite values.
        dropped_rows: rows the reader dropped in total (each row once), or ``None``
            when it did not count them (the N-CMAPSS / C-MAPSS readers do).
    """

    w: np.ndarray
    x: np.ndarray
    condition_names: tuple[str, ...]
    output_names: tuple[str, ...]
    unit: np.ndarray
    time: np.ndarray
    theta: np.ndarray | None = None
    theta_names: tuple[str, ...] = ()
    split: np.ndarray | None = None
    row: np.ndarray | None = None
    source: str = "arrays"
    dropped: dict | None = None
    dropped_rows: int | None = None

    def __post_init__(self):
        w = _float_matrix("w", self.w, None, self.condition_names)
        n = w.shape[0]
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen)
        set_("w", w)
        set_("x", _float_matrix("x", self.x, n, self.output_names))
        set_("condition_names", tuple(self.condition_names))
        set_("output_names", tuple(self.output_names))
        for field in ("unit", "time", "row"):
            value = getattr(self, field)
            if value is None and field == "row":
                value = np.arange(n)
            arr = np.asarray(value)
            if arr.shape != (n,):
                raise ValueError(f"Dataset.{field} must be [N={n}], got {arr.shape}")
            if field in ("unit", "row"):
                if arr.dtype.kind == "f" and np.any(arr != np.round(arr)):
                    raise ValueError(f"Dataset.{field} must hold integers")
                arr = arr.astype(np.int64)
            else:
                arr = arr.astype(np.float64)
            set_(field, arr)
        if self.theta is not None:
            set_("theta", _float_matrix("theta", self.theta, n, self.theta_names))
            set_("theta_names", tuple(self.theta_names))
        if self.split is not None:
            split = np.asarray(self.split).astype(str)
            if split.shape != (n,):
                raise ValueError(f"Dataset.split must be [N={n}], got {split.shape}")
            set_("split", split)
        set_("dropped", dict(self.dropped or {}))
        if self.dropped_rows is not None:
            set_("dropped_rows", int(self.dropped_rows))

    # ---------------------------------------------------------------- facts

    @property
    def num_rows(self) -> int:
        return int(self.w.shape[0])

    @property
    def partial(self) -> np.ndarray:
        """``[N]`` bool: rows with some outputs missing (:func:`partial_rows`)."""
        return partial_rows(self.x)

    @property
    def units(self) -> np.ndarray:
        """Unit ids in order of first appearance."""
        _, first = np.unique(self.unit, return_index=True)
        return self.unit[np.sort(first)]

    def __repr__(self) -> str:
        return (
            f"Dataset({self.num_rows} rows, {len(self.units)} units, W="
            f"{len(self.condition_names)}, S={len(self.output_names)}, theta="
            f"{list(self.theta_names) or None}, source={self.source!r})"
        )

    # ---------------------------------------------------------------- selection

    def take(self, rows: np.ndarray) -> Dataset:
        """The rows selected by a boolean mask or an index array."""
        rows = np.asarray(rows)
        pick = lambda a: None if a is None else a[rows]  # noqa: E731
        return dataclasses.replace(
            self,
            w=self.w[rows],
            x=self.x[rows],
            unit=self.unit[rows],
            time=self.time[rows],
            theta=pick(self.theta),
            split=pick(self.split),
            row=self.row[rows],
        )

    def select_units(self, units: Sequence[int]) -> Dataset:
        """The rows of ``units`` (an unknown unit id is an error)."""
        units = np.asarray(list(units), np.int64)
        missing = sorted(set(units.tolist()) - set(self.unit.tolist()))
        if missing:
            raise ValueError(
                f"{self.source}: unit(s) {missing} not in the data; units: "
                f"{self.units.tolist()}"
            )
        return self.take(np.isin(self.unit, units))

    def select_split(self, split: str) -> Dataset:
        """The rows labelled ``split`` (an error if there is no split column)."""
        if self.split is None:
            raise ValueError(f"{self.source}: the data have no split column")
        return self.take(self.split == split)

    def with_outputs(self, names: Sequence[str]) -> Dataset:
        """Only the output columns ``names``, in that order."""
        idx = names_to_index(names, self.output_names, f"{self.source} outputs")
        return dataclasses.replace(self, x=self.x[:, idx], output_names=tuple(names))

    def for_model(self, model: Model, outputs: Sequence[str] | None = None) -> Dataset:
        """Check the columns against ``model`` and order ``w`` as its conditions.

        Raises:
            ValueError: a condition or output of the model is missing from the data;
                the message lists what was expected and what was found.
        """
        missing = [n for n in model.condition_names if n not in self.condition_names]
        if missing:
            raise ValueError(
                f"{self.source}: missing condition column(s) {missing}; model "
                f"{model.name!r} expects conditions {list(model.condition_names)}, "
                f"found {list(self.condition_names)}"
            )
        idx = [self.condition_names.index(n) for n in model.condition_names]
        data = dataclasses.replace(
            self, w=self.w[:, idx], condition_names=model.condition_names
        )
        outputs = (
            list(outputs)
            if outputs
            else [n for n in data.output_names if n in model.output_names]
        )
        stray = [n for n in outputs if n not in model.output_names]
        absent = [n for n in outputs if n not in data.output_names]
        if stray or absent or not outputs:
            raise ValueError(
                f"{self.source}: outputs {stray or absent or '(none)'} cannot be used; "
                f"model {model.name!r} outputs {list(model.output_names)}, data "
                f"columns {list(data.output_names)}"
            )
        return data.with_outputs(outputs)

    # ---------------------------------------------------------------- padding

    def padded(self, dtype=np.float64) -> Padded:
        """Units as padded ``[U, T, ...]`` streams (rows sorted by time in a unit).

        Padding repeats a unit's last row (never zeros a model would choke on) and
        is masked out.
        """
        units = self.units
        unit_pos = np.searchsorted(np.sort(units), self.unit)
        # position of each unit in first-appearance order
        rank = np.empty(len(units), np.int64)
        rank[np.searchsorted(np.sort(units), units)] = np.arange(len(units))
        upos = rank[unit_pos]
        order = np.lexsort((self.time, upos))
        counts = np.bincount(upos, minlength=len(units))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.arange(len(order)) - starts[upos[order]]
        num, length = len(units), int(counts.max()) if len(units) else 0
        rows = np.full((num, length), -1, np.int64)
        rows[upos[order], slot] = order
        mask = rows >= 0
        fill = np.where(mask, rows, rows[np.arange(num), counts - 1][:, None])
        theta = None if self.theta is None else self.theta[fill].astype(dtype)
        return Padded(
            w=self.w[fill].astype(dtype),
            x=self.x[fill].astype(dtype),
            theta=theta,
            lengths=counts.astype(np.int32),
            unit_ids=np.asarray(units, np.int64),
            rows=rows,
        )


def partial_rows(x: np.ndarray) -> np.ndarray:
    """``[N]`` bool: rows of ``x [N, S]`` with some outputs missing (NaN) and the
    others finite — a sensor channel that dropped out. A row with an Inf or with no
    finite output is not partial (it is bad, not incomplete). The host twin of
    :func:`jaxcal.calibrators.guard.is_partial`."""
    x = np.asarray(x)
    missing = np.isnan(x)
    finite = np.isfinite(x)
    return missing.any(1) & (finite | missing).all(1) & finite.any(1)


def clip_jitter(
    w: np.ndarray, model: Model, fraction: float = JITTER_FRACTION
) -> tuple[np.ndarray, list[str]]:
    """Conditions just outside the model's range (within ``fraction`` of its width,
    e.g. a Mach of -0.0005 logged at a static point) set onto the bound, with a note
    per condition and bound saying on how many rows; farther ones are left for the
    sample guard to flag.

    Args:
        w: ``[N, W]`` conditions in the model's order.
        model: the model (its ``condition_range``).
        fraction: tolerance as a share of each condition's range width.

    Returns:
        ``(w, notes)``: a clipped copy and human-readable notes (empty: unchanged).
    """
    if model.condition_range is None:
        return w, []
    low, high = model.condition_range
    width = np.where(np.isfinite(high - low), high - low, np.inf)
    notes, w = [], np.array(w, copy=True)
    for j, name in enumerate(model.condition_names):
        tol = fraction * width[j]
        for bound, outside in (
            (low[j], (w[:, j] < low[j]) & (w[:, j] >= low[j] - tol)),
            (high[j], (w[:, j] > high[j]) & (w[:, j] <= high[j] + tol)),
        ):
            if outside.any():
                notes.append(
                    f"{name} just outside its range (jitter) set to {bound:g} on "
                    f"{int(outside.sum())} rows"
                )
                w[outside, j] = bound
    return w, notes
