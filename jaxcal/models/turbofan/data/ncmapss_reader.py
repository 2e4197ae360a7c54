"""Reader of N-CMAPSS HDF5 files (ours and NASA's): column order from the ``*_var``
names, subsets by slicing (layout: :mod:`jaxcal.models.turbofan.data.ncmapss_io`).

Column names are checked, never guessed
(:mod:`jaxcal.models.turbofan.data.ncmapss_columns`): a renamed sensor (``T_24`` for
``T24``) is an error that lists what was expected and what was found, unless the caller
maps it with ``rename={"T_24": "T24"}``. Rows holding NaN or Inf in a returned column
follow the ``nonfinite`` policy of :data:`~jaxcal.data.table_checks.NONFINITE_POLICIES`
(default: refuse them).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from jaxcal.data.table_checks import apply_nonfinite_policy, check_nonfinite_policy
from jaxcal.models.turbofan.data.ncmapss_columns import (
    column_names,
    open_read,
    split_layout,
)
from jaxcal.models.turbofan.data.ncmapss_layout import _BLOCK_ROWS, SPLITS, _dtype
from jaxcal.models.turbofan.data.record import Record
from jaxcal.models.turbofan.physics.constants import (
    AUX_NAMES,
    CONDITION_NAMES,
    HEALTH_NAMES,
    SENSOR_NAMES,
)


def _unit_ranges(a_dset, unit_col, wanted, start, stop, block_rows):
    """Maximal ``[a, b)`` row ranges whose unit is in ``wanted``, and all units seen.

    Only column ``unit_col`` of ``A`` is read, ``block_rows`` rows at a time.
    """
    ranges: list[list[int]] = []
    seen: set[int] = set()
    for a0 in range(start, stop, block_rows):
        units = a_dset[a0 : min(stop, a0 + block_rows), unit_col]
        # A NaN unit id names no unit; the nonfinite policy reports its rows on load.
        seen.update(int(u) for u in np.unique(units) if np.isfinite(u))
        edges = np.diff(
            np.concatenate([[0], np.isin(units, wanted).astype(np.int8), [0]])
        )
        run_starts = np.flatnonzero(edges == 1) + a0
        run_stops = np.flatnonzero(edges == -1) + a0
        for a, b in zip(run_starts, run_stops, strict=True):
            if ranges and ranges[-1][1] == a:
                ranges[-1][1] = int(b)  # a unit that straddles two scan blocks
            else:
                ranges.append([int(a), int(b)])
    return ranges, seen


def _read_into(dset, ranges, stride, cols, out, block_rows) -> None:
    """Fill ``out`` with ``dset[a:b:stride][:, cols]`` over ``ranges``, by blocks."""
    pos = 0
    for a, b in ranges:
        for a0 in range(a, b, block_rows * stride):
            block = dset[a0 : min(b, a0 + block_rows * stride) : stride]
            out[pos : pos + block.shape[0]] = block[:, cols]
            pos += block.shape[0]


def _checked_read_options(stride, block_rows, nonfinite: str) -> tuple[int, int]:
    """``(stride, block_rows)`` as ints, each checked, and the nonfinite policy."""
    if int(stride) != stride or stride < 1:
        raise ValueError(f"stride must be an integer >= 1, got {stride}")
    if int(block_rows) < 1:
        raise ValueError(f"block_rows must be >= 1, got {block_rows}")
    check_nonfinite_policy(nonfinite)
    return int(stride), int(block_rows)


def _selected_ranges(layout: dict, units, rows, stride: int, block_rows: int, where):
    """The ``[a, b)`` file row ranges to read: the window ``rows``, only the rows of
    ``units`` (each must be there), every range aligned to the stride grid of the
    window start (so a unit selection sees exactly the rows the full load would)."""
    dsets, names = layout["dsets"], layout["names"]
    start, stop = _row_window(rows, layout["num_rows"])
    if units is None:
        ranges = [[start, stop]]
    else:
        wanted = _unit_ids(units)
        ranges, seen = _unit_ranges(
            dsets["A"], names["A"].index("unit"), wanted, start, stop, block_rows
        )
        missing = sorted(set(wanted.astype(int).tolist()) - seen)
        if missing:
            raise ValueError(
                f"{where} rows {start}:{stop} has no unit(s) {missing}; "
                f"units there are {sorted(seen)}"
            )
    # Align every range to the global stride grid start, start + stride, ...
    ranges = [[a + (start - a) % stride, b] for a, b in ranges]
    return [[a, b] for a, b in ranges if a < b]


def _read_columns(layout: dict, ranges, stride: int, sensors, path, block_rows: int):
    """Every returned column over ``ranges``: ``(x_names, w, x, theta, aux, rul)``,
    the sensors' groups read only when a requested sensor is in them."""
    dsets, names = layout["dsets"], layout["names"]
    total = sum(len(range(a, b, stride)) for a, b in ranges)

    def read(group, cols):
        out = np.empty((total, len(cols)), dtype=_dtype(group))
        _read_into(dsets[group], ranges, stride, cols, out, block_rows)
        return out

    x_names, plan = _sensor_plan(names, sensors, path)
    x = np.empty((total, len(x_names)), dtype=np.float64)
    for group in ("X_s", "X_v"):
        picks = [(j, c) for j, (g, c) in enumerate(plan) if g == group]
        if not picks:
            continue  # this group is not needed: do not touch it on disk
        x[:, [j for j, _ in picks]] = read(group, [c for _, c in picks])
    w = read("W", [names["W"].index(n) for n in CONDITION_NAMES])
    theta = read("T", [names["T"].index(n) for n in HEALTH_NAMES])
    aux = read("A", [names["A"].index(n) for n in AUX_NAMES])
    rul = read("Y", [0])[:, 0]
    return x_names, w, x, theta, aux, rul


def load_ncmapss(
    path,
    split: str = "dev",
    units=None,
    sensors=None,
    rows: tuple[int, int] | None = None,
    stride: int = 1,
    *,
    rename: Mapping[str, str] | None = None,
    nonfinite: str = "error",
    block_rows: int = _BLOCK_ROWS,
) -> Record:
    """Load (part of) one split of an N-CMAPSS file, ours or NASA's.

    Args:
        path: the ``.h5`` file.
        split: ``"dev"`` or ``"test"``.
        units: unit ids to keep (``None``: all). Rows come back in file order.
        sensors: sensor names of ``X_s_var`` / ``X_v_var`` to load, in this order
            (``None``: all of them, in :data:`SENSOR_NAMES` order).
        rows: ``(start, stop)`` window of file rows to consider (``None``: all).
        stride: keep file rows ``start, start + stride, ...`` (aligned to the window
            start, so a unit selection sees exactly the rows the full load would).
        rename: ``{file column name: jaxcal name}`` for files that spell columns
            otherwise (e.g. ``{"T_24": "T24"}``); every ``*_var`` group must then
            hold the layout's names (else a ValueError lists expected and found).
        nonfinite: rows with NaN / Inf in a returned column (w, the loaded sensors,
            theta, unit, cycle): ``"error"`` refuses them (ValueError naming the file,
            each column, its first file rows, 0-based in the split, and its count),
            ``"drop"`` drops them and reports them in ``Record.dropped``,
            ``"keep"`` returns them for a caller that guards each sample.
        block_rows: rows per read block (bounds memory; small values only for tests).

    Returns:
        A :class:`Record` whose ``sample_rate_hz`` is the file's ``sample_rate_hz`` root
        attribute (1.0 when absent, as in NASA's files) divided by ``stride``.
    """
    stride, block_rows = _checked_read_options(stride, block_rows, nonfinite)
    path, f = open_read(path)
    with f:
        layout = split_layout(f, path, split, column_names(f, path, rename))
        ranges = _selected_ranges(
            layout, units, rows, stride, block_rows, f"{path} [{split}]"
        )
        x_names, w, x, theta, aux, rul = _read_columns(
            layout, ranges, stride, sensors, path, block_rows
        )
        rate = float(f.attrs.get("sample_rate_hz", 1.0))
    keep, dropped = _nonfinite_rows(
        w, x, x_names, theta, aux, nonfinite, f"{path} [{split}]", ranges, stride
    )
    num_dropped = 0
    if keep is not None:
        # Drop before building the Record: a NaN unit or cycle is no integer id.
        num_dropped = int(keep.size - keep.sum())
        w, x, theta, aux, rul = (a[keep] for a in (w, x, theta, aux, rul))
    return Record(
        w=w,
        x=x,
        x_names=x_names,
        theta=theta,
        unit=aux[:, 0],
        cycle=aux[:, 1],
        flight_class=aux[:, 2],
        hs=aux[:, 3],
        rul=rul,
        sample_rate_hz=rate / stride,
        source=f"{path}[{split}]",
        dropped=dropped,
        dropped_rows=num_dropped,
    )


def _file_rows(ranges, stride: int):
    """Positions in the loaded arrays -> 0-based rows of the split's datasets."""
    starts = np.array([a for a, _ in ranges], np.int64)
    counts = np.array([len(range(a, b, stride)) for a, b in ranges], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])

    def row_of(pos: np.ndarray) -> np.ndarray:
        i = np.searchsorted(offsets, pos, side="right") - 1
        return starts[i] + (pos - offsets[i]) * stride

    return row_of


def _nonfinite_rows(w, x, x_names, theta, aux, policy, source, ranges, stride):
    """``(keep [N] bool or None, dropped)`` of the loaded columns under ``policy``."""
    columns = {n: w[:, j] for j, n in enumerate(CONDITION_NAMES)}
    columns.update({n: x[:, j] for j, n in enumerate(x_names)})
    columns.update({n: theta[:, j] for j, n in enumerate(HEALTH_NAMES)})
    ids = {"unit": aux[:, 0], "cycle": aux[:, 1]}
    where = f"{source} (rows counted from 0 in the split's arrays)"
    row_of = _file_rows(ranges, stride)
    if policy == "keep":
        # A row without a unit or cycle cannot be kept: refuse it even here.
        apply_nonfinite_policy(ids, "error", source=where, row_of=row_of)
        return None, {}
    return apply_nonfinite_policy(
        {**columns, **ids}, policy, source=where, row_of=row_of
    )


def _unit_ids(units) -> np.ndarray:
    """Requested unit ids as sorted unique floats (A stores units as float64)."""
    ids = np.asarray(list(np.atleast_1d(units)))
    if ids.size == 0:
        raise ValueError("units must name at least one unit id (or be None for all)")
    if ids.dtype.kind not in "iuf" or np.any(ids != np.round(ids)):
        raise ValueError(f"units must be integer unit ids, got {units!r}")
    return np.unique(ids.astype(np.float64))


def _row_window(rows, num_rows: int) -> tuple[int, int]:
    if rows is None:
        return 0, num_rows
    start, stop = (int(r) for r in rows)
    if not 0 <= start <= stop <= num_rows:
        raise ValueError(
            f"rows must be (start, stop) with 0 <= start <= stop <= {num_rows}, "
            f"got {rows}"
        )
    return start, stop


def _sensor_plan(names: dict, sensors, path: str):
    """Where requested sensors live: ``(x_names, [(group, col)])``."""
    where = {}
    for group in ("X_s", "X_v"):
        for col, name in enumerate(names[group]):
            where[name] = (group, col)  # names are unique (column_names checks)
    if sensors is None:
        x_names = tuple(n for n in SENSOR_NAMES if n in where)
    else:
        if isinstance(sensors, str):
            raise ValueError(
                f"sensors must be a sequence of names, got the string {sensors!r}"
            )
        x_names = tuple(sensors)
        missing = [n for n in x_names if n not in where]
        if missing:
            raise ValueError(
                f"{path}: sensor(s) {missing} not in X_s_var / X_v_var; available: "
                f"{list(where)}"
            )
    return x_names, [where[n] for n in x_names]


def ncmapss_info(
    path, *, rename: Mapping[str, str] | None = None, block_rows: int = _BLOCK_ROWS
) -> dict:
    """Summary of an N-CMAPSS file without loading its arrays.

    Args:
        path: the ``.h5`` file.
        rename: ``{file column name: jaxcal name}``, as for :func:`load_ncmapss`.
        block_rows: rows per block when scanning the unit column.

    Returns:
        ``{"path", "columns": {group: names}, "attrs": {...}, "sample_rate_hz",
        "splits": {split: {"rows": N, "units": [...]}}}``; a split appears when its
        ``A_<split>`` dataset exists.
    """
    path, f = open_read(path)
    with f:
        columns = column_names(f, path, rename)
        splits = {}
        for split in SPLITS:
            if f"A_{split}" not in f:
                continue
            layout = split_layout(f, path, split, columns)
            n = layout["num_rows"]
            _, seen = _unit_ranges(
                layout["dsets"]["A"],
                columns["A"].index("unit"),
                np.empty(0),
                0,
                n,
                block_rows,
            )
            splits[split] = {"rows": int(n), "units": sorted(seen)}
        if not splits:
            raise ValueError(f"{path}: no split found (expected A_dev and/or A_test)")
        attrs = {k: _plain(v) for k, v in f.attrs.items()}
    return {
        "path": path,
        "columns": columns,
        "attrs": attrs,
        "sample_rate_hz": float(attrs.get("sample_rate_hz", 1.0)),
        "splits": splits,
    }


def _plain(value):
    """An HDF5 attribute value as a plain Python value (JSON-friendly)."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
