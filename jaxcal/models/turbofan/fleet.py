"""N-CMAPSS files as a stream of unit chunks for :mod:`jaxcal.fleet.streaming`.

A file may be far larger than memory (the AGTF30 set is 2.4 GB; NASA's DS files hold
up to ~10 M rows), so nothing here reads a whole split: :func:`unit_lengths` scans only
the unit column of ``A_<split>`` in blocks, :func:`iter_ncmapss_chunks` reads one chunk
of units at a time, padded to the fixed length ``T`` that keeps the compiled program
unique (:func:`~jaxcal.models.turbofan.data.datasets.read_ncmapss_padded`, which reads
only the rows of the requested units), and :func:`sensor_norm` takes the outputs'
normalisation (their mean and std) from the file's reference statistics or, failing
those, from one blocked pass over the sensor columns.

Row selection with ``stride`` keeps file rows ``0, stride, 2 stride, ...`` (the grid of
``load_ncmapss`` for a unit selection), here and in the lengths.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence

import h5py
import numpy as np

from jaxcal.fleet.sources import FleetSource, clean_rows, unit_positions
from jaxcal.fleet.streaming import UnitChunk, plan_chunks
from jaxcal.model import Model
from jaxcal.models.turbofan.data.datasets import (
    read_ncmapss_padded,
    read_ncmapss_split,
)
from jaxcal.models.turbofan.physics.constants import (
    CONDITION_NAMES,
    MEASURED_SENSOR_NAMES,
    health_index,
)
from jaxcal.precision import float_dtype

_BLOCK_ROWS = 1 << 20  # rows per read block of the unit scan and the statistics pass
NCMAPSS_EXTENSIONS = (".h5", ".hdf5")
NCMAPSS_DEFAULT_SPLIT = "test"


def _check_stride(stride: int) -> int:
    if int(stride) != stride or stride < 1:
        raise ValueError(f"stride must be an integer >= 1, got {stride}")
    return int(stride)


def unit_lengths(
    path,
    split: str = "dev",
    units: Sequence[int] | None = None,
    *,
    stride: int = 1,
    block_rows: int = _BLOCK_ROWS,
) -> tuple[np.ndarray, np.ndarray]:
    """Unit ids and their row counts, from the unit column alone.

    Args:
        path: the ``.h5`` file. split: ``"dev"`` or ``"test"``.
        units: ids to keep (``None``: all units of the split).
        stride: count only rows ``0, stride, ...`` of the file.
        block_rows: rows per read block (bounds memory).

    Returns:
        ``(unit_ids [U] int64 ascending, lengths [U] int64)``.
    """
    stride = _check_stride(stride)
    block_rows = max(stride, int(block_rows) // stride * stride)  # keep the grid
    path = os.fspath(path)
    with h5py.File(path, "r") as f:
        if f"A_{split}" not in f or "A_var" not in f:
            raise ValueError(f"{path}: no A_{split} / A_var datasets (split={split!r})")
        names = [n.decode().strip() for n in f["A_var"][()]]
        if "unit" not in names:
            raise ValueError(f"{path}: A_var has no 'unit' column, got {names}")
        col, dset = names.index("unit"), f[f"A_{split}"]
        counts: dict[int, int] = {}
        for a in range(0, dset.shape[0], block_rows):
            ids = dset[a : a + block_rows][::stride, col]
            found, num = np.unique(ids.astype(np.int64), return_counts=True)
            for unit, n in zip(found.tolist(), num.tolist(), strict=True):
                counts[unit] = counts.get(unit, 0) + n
    if units is not None:
        wanted = sorted({int(u) for u in np.atleast_1d(units)})
        missing = [u for u in wanted if u not in counts]
        if missing or not wanted:
            raise ValueError(
                f"{path} [{split}] has no unit(s) {missing or '(none requested)'}; "
                f"units there are {sorted(counts)}"
            )
        counts = {u: counts[u] for u in wanted}
    ids = np.array(sorted(counts), np.int64)
    return ids, np.array([counts[u] for u in ids.tolist()], np.int64)


def iter_ncmapss_chunks(
    path,
    split: str,
    unit_ids: np.ndarray,
    *,
    max_len: int,
    chunk_units: int,
    sensors: Sequence[str],
    theta_names: Sequence[str] | None = None,
    stride: int = 1,
    process_index: int = 0,
    num_processes: int = 1,
) -> Iterator[UnitChunk]:
    """This process's share of every chunk of ``unit_ids``, read from the file.

    Args:
        path, split: the N-CMAPSS file and split.
        unit_ids: ``[U]`` ids in the global order (e.g. from :func:`unit_lengths`).
        max_len: ``T``, the padded length; a longer unit is an error, never truncated.
        chunk_units: units per global chunk.
        sensors: sensor names, the ``S`` columns of ``x``.
        theta_names: declared parameters; their true values (``T_<split>``) are
            passed on as the per-step extra ``theta_true``. ``None``: no truth.
        stride: keep file rows ``0, stride, ...``.
        process_index, num_processes: this process and the process count.

    Yields:
        :class:`~jaxcal.fleet.streaming.UnitChunk` s with ``w [u, T, 4]``,
        ``x [u, T, S]``, ``cycle`` and (optionally) ``theta_true [u, T, P]``.
    """
    unit_ids = np.asarray(unit_ids, np.int64)
    truth_idx = None if theta_names is None else health_index(list(theta_names))
    for parts in plan_chunks(unit_ids.size, chunk_units, num_processes):
        pos = parts[process_index]
        index = pos
        if pos.size == 0:  # collective program: run on a copy, discard the results
            pos, index = parts[0][:1], np.full(1, -1)
        # NaN / Inf samples are kept: the runners skip and flag them one by one
        # (dropping here would shift rows against unit_lengths).
        fleet = read_ncmapss_padded(
            path,
            split,
            max_len=max_len,
            dtype=float_dtype(),
            units=unit_ids[pos],
            sensors=list(sensors),
            stride=stride,
            nonfinite="keep",
        )
        extras = None
        if truth_idx is not None:
            extras = {"theta_true": np.asarray(fleet.theta)[..., truth_idx]}
        yield UnitChunk(
            index=index.astype(np.int64),
            unit_ids=np.asarray(fleet.unit_ids, np.int64),
            w=np.asarray(fleet.w),
            x=np.asarray(fleet.x),
            mask=np.asarray(fleet.mask),
            cycle=np.asarray(fleet.cycle, np.int64),
            extras=extras,
        )


def sensor_norm(
    path,
    split: str,
    sensors: Sequence[str],
    units: Sequence[int] | None = None,
    *,
    stride: int = 1,
    block_rows: int = _BLOCK_ROWS,
) -> tuple[tuple[np.ndarray, np.ndarray], str]:
    """Per-sensor mean / std: the outputs' normalisation (the ``x`` part of the
    problem's :class:`~jaxcal.data.normalisation.Normalisation`: its mean centres
    the outputs the UKF and least squares compare, the turbofan's default noise
    without ``noise=`` is 1 % of its std; :func:`jaxcal.fleet.method.build_problem`).

    Uses the file's ``reference_x_names`` / ``reference_x_mean`` / ``reference_x_std``
    root attributes (written by ``jaxcal.generate``: statistics of the noise-free
    reference fleet) when they cover ``sensors``; otherwise one blocked pass over the
    selected units' rows of the split.

    Returns:
        ``((mean [S], std [S]), source)`` with ``source`` ``"file attributes"`` or
        ``"data pass"``.
    """
    stride = _check_stride(stride)
    path = os.fspath(path)
    with h5py.File(path, "r") as f:
        attrs = dict(f.attrs)
        num_rows = f[f"A_{split}"].shape[0] if f"A_{split}" in f else 0
    if all(k in attrs for k in ("reference_x_names", "reference_x_mean")) and (
        "reference_x_std" in attrs
    ):
        names = attrs["reference_x_names"]
        names = json.loads(names) if isinstance(names, str | bytes) else list(names)
        if all(s in names for s in sensors):
            cols = [names.index(s) for s in sensors]
            mean = np.asarray(attrs["reference_x_mean"], np.float64)[cols]
            std = np.asarray(attrs["reference_x_std"], np.float64)[cols]
            return (mean, std), "file attributes"
    block_rows = max(stride, int(block_rows) // stride * stride)
    wanted = None if units is None else np.asarray(list(units), np.int64)
    total, sums, squares = 0, 0.0, 0.0
    for a in range(0, num_rows, block_rows):
        # statistics of the finite rows only: one NaN would poison the mean
        block = read_ncmapss_split(
            path, split, label=False, sensors=list(sensors),
            rows=(a, min(a + block_rows, num_rows)), stride=stride, nonfinite="drop",
        )  # fmt: skip
        x = block.x if wanted is None else block.x[np.isin(block.unit, wanted)]
        total += x.shape[0]
        sums = sums + x.sum(axis=0)
        squares = squares + np.square(x).sum(axis=0)
    if total == 0:
        raise ValueError(f"{path} [{split}]: no rows to compute sensor statistics on")
    mean = sums / total
    std = np.sqrt(np.maximum(squares / total - np.square(mean), 0.0))
    # A scale-aware floor: constant columns must not blow up after normalisation.
    std = np.maximum(std, 1e-6 * np.maximum(1.0, np.abs(mean)))
    return (mean, std), "data pass"


def is_ncmapss(path: str) -> bool:
    """A file the fleet streams in the N-CMAPSS layout (by its extension)."""
    return os.path.splitext(os.fspath(path))[1].lower() in NCMAPSS_EXTENSIONS


def file_sensors(path: str) -> tuple[str, ...]:
    """An N-CMAPSS file's ``observed_sensors`` attribute, else its measured sensors
    ``X_s``."""
    with h5py.File(path, "r") as f:
        observed = f.attrs.get("observed_sensors")
        names = [n.decode().strip() for n in f["X_s_var"][()]] if "X_s_var" in f else []
    if isinstance(observed, bytes):
        observed = observed.decode()
    if isinstance(observed, str) and observed:
        return tuple(json.loads(observed))
    return tuple(n for n in names if n in MEASURED_SENSOR_NAMES)


def open_ncmapss(
    path: str, model: Model, *, outputs: Sequence[str] = (), split: str = "",
    units: Sequence[int] = (), stride: int = 1, max_len: int = 0,
) -> FleetSource:  # fmt: skip
    """The streamed :class:`~jaxcal.fleet.sources.FleetSource` of an N-CMAPSS file
    (arguments: :func:`jaxcal.fleet.sources.open_source`'s; ``split`` ``dev`` /
    ``test``, default ``test``; ``outputs`` default: the file's ``observed_sensors``
    else ``X_s``): the problem is built on the first selected unit's rows with the
    outputs' statistics of :func:`sensor_norm`; nothing reads the whole split."""
    if not os.path.isfile(path):
        raise ValueError(f"data file not found: {path}")
    if tuple(model.condition_names) != tuple(CONDITION_NAMES):
        raise ValueError(
            f"{path}: an N-CMAPSS file holds the turbofan's conditions "
            f"{list(CONDITION_NAMES)}; model {model.name!r} has "
            f"{list(model.condition_names)}: give its data as a table (.csv, .parquet)"
        )
    split = split or NCMAPSS_DEFAULT_SPLIT
    outputs = tuple(outputs) or file_sensors(path)
    wanted = list(units) or None
    unit_ids, lengths = unit_lengths(path, split, wanted, stride=stride)
    length = max_len or int(lengths.max())
    x_stats, norm_source = sensor_norm(path, split, outputs, wanted, stride=stride)
    first = read_ncmapss_split(
        path, split, units=unit_ids[:1], sensors=list(outputs), stride=stride,
        nonfinite="keep",
    )  # fmt: skip
    sample = clean_rows(first.for_model(model, outputs))

    def chunks(theta_names, chunk_units, process_index=0, num_processes=1, units=None):
        truth = sample.theta is not None and set(theta_names) <= set(sample.theta_names)
        ids = unit_ids[unit_positions(unit_ids, units)]
        return iter_ncmapss_chunks(
            path, split, ids, max_len=length, chunk_units=chunk_units,
            sensors=outputs, theta_names=tuple(theta_names) if truth else None,
            stride=stride, process_index=process_index, num_processes=num_processes,
        )  # fmt: skip

    return FleetSource(
        sample=sample, outputs=outputs, x_stats=x_stats, unit_ids=unit_ids,
        max_len=length, description=f"{path}[{split}]", norm_source=norm_source,
        chunks=chunks, complete=False,
    )  # fmt: skip
