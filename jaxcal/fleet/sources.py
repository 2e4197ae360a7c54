"""The data of a fleet run: a sample to build the problem on, and a stream of chunks.

``python -m jaxcal.fleet`` reads two kinds of source:

* an **N-CMAPSS HDF5 file** (``.h5`` / ``.hdf5``; the turbofan's layout) is streamed:
  the unit column is scanned for the units and their lengths, the output statistics
  come from the file's reference attributes or one blocked pass, and the problem is
  built on the rows of the first selected unit with those statistics; nothing reads
  the whole split (:func:`jaxcal.models.turbofan.fleet.open_ncmapss`, the turbofan's);
* any other data source of the front door (CSV, Parquet, NASA C-MAPSS ``.txt``:
  :func:`jaxcal.data.readers.read_dataset`) is a table held in memory
  (:func:`open_source`): the problem is built on all its rows and the chunks are cut
  from its padded units (:func:`~jaxcal.fleet.streaming.iter_array_chunks`).

Rows with NaN / Inf are kept in both (the runners skip and flag them one by one, so
the output has one row per input row); the problem is built on the clean rows.
Units come in ascending id, rows in time order within a unit.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import NamedTuple

import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.data.readers import read_dataset
from jaxcal.fleet.streaming import UnitChunk, iter_array_chunks
from jaxcal.model import Model


class FleetSource(NamedTuple):
    """What a fleet run reads.

    Attributes:
        sample: the rows the problem is built on (the whole table, or the first unit
            of an N-CMAPSS file), columns checked against the model.
        outputs: the outputs used, the columns of the chunks' ``x``.
        x_stats: the outputs' normalisation ``(mean [S], std [S])`` over every
            selected row (or the file's reference statistics) when ``sample`` is
            only part of the data (N-CMAPSS), else ``None``.
        unit_ids: ``[U]`` selected unit ids, ascending.
        max_len: ``T``, the padded length.
        description: ``path[split]`` for the output file.
        norm_source: where the outputs' statistics come from.
        chunks: ``chunks(theta_names, chunk_units, process_index, num_processes,
            units=None)`` -> this process's :class:`UnitChunk` s of the units
            ``units`` (ids among ``unit_ids``, ascending; ``None``: every one), with
            ``theta_true`` when the data hold the true values of ``theta_names``.
        complete: ``sample`` is all the data (a table).
    """

    sample: Dataset
    outputs: tuple[str, ...]
    x_stats: tuple[np.ndarray, np.ndarray] | None
    unit_ids: np.ndarray
    max_len: int
    description: str
    norm_source: str
    chunks: Callable[..., Iterator[UnitChunk]]
    complete: bool


def clean_rows(data: Dataset) -> Dataset:
    """The rows a problem can be built on: finite conditions, outputs finite or
    missing (a partial row)."""
    ok = np.isfinite(data.w).all(axis=1)
    ok &= np.isfinite(data.x).all(axis=1) | data.partial
    if not ok.any():
        raise ValueError(f"{data.source}: no row with finite values")
    return data if ok.all() else data.take(ok)


def open_source(
    path: str,
    model: Model,
    *,
    outputs: Sequence[str] = (),
    split: str = "",
    units: Sequence[int] = (),
    stride: int = 1,
    max_len: int = 0,
) -> FleetSource:
    """The :class:`FleetSource` of a table (module docstring).

    Args:
        path: any file :func:`~jaxcal.data.readers.read_dataset` reads.
        model: the model whose names the columns follow.
        outputs: outputs to use (``()``: every model output of the table).
        split: the label of a table's ``split`` column (default: every row).
        units: unit ids to keep (``()``: all).
        stride: keep file rows ``0, stride, 2 stride, ...``.
        max_len: padded length ``T`` (0: the longest selected unit).

    Raises:
        ValueError: unreadable data, names that do not match the model, unknown
            units, a unit longer than ``max_len``.
    """
    if not os.path.isfile(path):
        raise ValueError(f"data file not found: {path}")
    return _table(path, model, outputs, split, units, stride, max_len)


def unit_positions(unit_ids: np.ndarray, units) -> np.ndarray:
    """The positions in ``unit_ids`` of the ids ``units`` (``None``: every one).

    Raises:
        ValueError: naming ids that are not among ``unit_ids``.
    """
    if units is None:
        return np.arange(unit_ids.size)
    units = np.asarray(units, np.int64)
    missing = sorted(set(units.tolist()) - set(unit_ids.tolist()))
    if missing:
        raise ValueError(f"chunks: unit(s) {missing} are not among the selected units")
    return np.flatnonzero(np.isin(unit_ids, units))


def _table(path, model, outputs, split, units, stride, max_len) -> FleetSource:
    data = read_dataset(path, model, nonfinite="keep").for_model(model, outputs)
    if split:
        data = data.select_split(split)
    if units:
        data = data.select_units(units)
    if stride > 1:  # file rows 0, stride, ...: the grid whatever the selection
        data = data.take(data.row % stride == 0)
    padded = data.padded(np.float64)
    order = np.argsort(padded.unit_ids, kind="stable")  # ascending unit ids
    rows, mask = padded.rows[order], padded.mask[order]
    longest = int(mask.sum(axis=1).max())
    length = max_len or longest
    if length < longest:
        raise ValueError(
            f"max_len={length} is shorter than a unit of {longest} rows; raise "
            "max_len (0 = longest)"
        )
    pad = ((0, 0), (0, length - rows.shape[1]))
    rows = np.pad(rows, pad, constant_values=-1)
    mask = np.pad(mask, pad, constant_values=False)
    last = rows[np.arange(rows.shape[0]), mask.sum(axis=1) - 1]
    fill = np.where(mask, rows, last[:, None])  # padding repeats a unit's last row
    unit_ids = padded.unit_ids[order]
    per_step = {
        "row": np.where(mask, data.row[fill], -1),  # the source's row of each step
        "time": data.time[fill],
    }

    def chunks(theta_names, chunk_units, process_index=0, num_processes=1, units=None):
        pos = unit_positions(unit_ids, units)
        rows = fill[pos]
        extras = {k: v[pos] for k, v in per_step.items()}
        if data.theta is not None and set(theta_names) <= set(data.theta_names):
            cols = [data.theta_names.index(n) for n in theta_names]
            extras["theta_true"] = data.theta[rows][..., cols]
        return iter_array_chunks(
            data.w[rows], data.x[rows], mask[pos], chunk_units, unit_ids=unit_ids[pos],
            extras=extras, process_index=process_index, num_processes=num_processes,
        )  # fmt: skip

    label = f"[{split}]" if split else ""
    return FleetSource(
        sample=clean_rows(data), outputs=data.output_names, x_stats=None,
        unit_ids=unit_ids, max_len=length, description=f"{path}{label}",
        norm_source="data (every selected row)", chunks=chunks, complete=True,
    )  # fmt: skip
