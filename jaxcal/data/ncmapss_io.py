"""Reading and writing the N-CMAPSS HDF5 layout (Arias Chao et al. 2021, NASA data set).

The layout is that of the real files (``N-CMAPSS_DS01-005.h5`` ...): per split ``dev`` /
``test`` the float64 datasets ``W_<split> [N, 4]``, ``X_s_<split> [N, 14]``,
``X_v_<split> [N, 14]``, ``T_<split> [N, 10]``, ``A_<split> [N, 4]`` (unit, cycle, Fc,
hs) and the int64 RUL ``Y_<split> [N, 1]``, plus fixed-width byte-string column names
``W_var``, ``X_s_var``, ``X_v_var``, ``T_var``, ``A_var`` (data_facts.md §2.1). Real
files have no root attributes and are sampled at 1 Hz; ours add ``sample_rate_hz`` (and
whatever ``attrs`` the caller passes, e.g. the generator config as JSON).

The reader never assumes a column order: it maps columns by the ``*_var`` names. Subsets
are read by slicing: selecting units scans only the unit column of ``A`` in blocks,
finds the contiguous row ranges of the wanted units, and reads only those rows, so a
unit of a 3 GB file costs about what its own rows cost. Writers are atomic: they fill a
temporary file in the destination directory and ``os.replace`` it into place only when
everything succeeded.
"""

from __future__ import annotations

import itertools
import json
import os
import tempfile

import h5py
import numpy as np

from jaxcal.data.record import Record
from jaxcal.physics.constants import (
    AUX_NAMES,
    CONDITION_NAMES,
    HEALTH_NAMES,
    MEASURED_SENSOR_NAMES,
    SENSOR_NAMES,
    VIRTUAL_SENSOR_NAMES,
)

SPLITS: tuple[str, ...] = ("dev", "test")
# Column names written to ``<group>_var``; the order is that of the real files.
LAYOUT_NAMES: dict[str, tuple[str, ...]] = {
    "W": CONDITION_NAMES,
    "X_s": MEASURED_SENSOR_NAMES,
    "X_v": VIRTUAL_SENSOR_NAMES,
    "T": HEALTH_NAMES,
    "A": AUX_NAMES,
}
_GROUPS: tuple[str, ...] = ("W", "X_s", "X_v", "T", "Y", "A")
# Rows per read / write block: ~110 MB for a 14-column float64 group.
_BLOCK_ROWS = 1 << 20
# HDF5 chunk of growable datasets: 14 columns -> 0.9 MB, inside the 1 MB chunk cache.
_CHUNK_ROWS = 8192


def _width(group: str) -> int:
    return 1 if group == "Y" else len(LAYOUT_NAMES[group])


def _dtype(group: str):
    return np.int64 if group == "Y" else np.float64


def _check_split(split: str) -> None:
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")


# --------------------------------------------------------------------------- writing


def _check_layout(record: Record, split: str) -> None:
    """Raise if ``record`` cannot fill the N-CMAPSS arrays of ``split``."""
    if not isinstance(record, Record):
        raise ValueError(
            f"the {split} data must be a Record, got {type(record).__name__}"
        )
    missing = [
        n
        for n in MEASURED_SENSOR_NAMES + VIRTUAL_SENSOR_NAMES
        if n not in record.x_names
    ]
    if missing:
        raise ValueError(
            f"the {split} record lacks sensor column(s) {missing}; the N-CMAPSS "
            f"layout needs X_s = {list(MEASURED_SENSOR_NAMES)} and "
            f"X_v = {list(VIRTUAL_SENSOR_NAMES)}"
        )
    if record.theta is None:
        raise ValueError(
            f"the {split} record has theta=None; the N-CMAPSS layout needs T"
        )


def _layout_arrays(record: Record) -> dict[str, np.ndarray]:
    """The six N-CMAPSS arrays of a (checked) record; ``A`` = (unit, cycle, Fc, hs)."""
    aux = np.stack([record.unit, record.cycle, record.flight_class, record.hs], axis=1)
    return {
        "W": record.w,
        "X_s": record.columns(MEASURED_SENSOR_NAMES),
        "X_v": record.columns(VIRTUAL_SENSOR_NAMES),
        "T": record.theta,
        "Y": record.rul[:, None],
        "A": aux.astype(np.float64),
    }


def _check_attrs(attrs: dict | None) -> dict:
    """Root attributes as HDF5-storable values (dicts / lists become JSON strings)."""
    out = {}
    for key, value in (attrs or {}).items():
        if not isinstance(key, str) or key == "sample_rate_hz":
            raise ValueError(
                f"attrs key {key!r} is not allowed: keys are strings and "
                "'sample_rate_hz' is taken from the records"
            )
        if isinstance(value, dict | list | tuple):
            value = json.dumps(value, sort_keys=True)
        elif not isinstance(value, str | bool | int | float | np.generic | np.ndarray):
            raise ValueError(
                f"attrs[{key!r}] must be a str, number, numpy array, or JSON-able "
                f"dict/list, got {type(value).__name__}"
            )
        out[key] = value
    return out


def _same_rate(a: float, b: float) -> bool:
    return (np.isnan(a) and np.isnan(b)) or a == b


class NCMAPSSWriter:
    """Appendable, atomic writer of an N-CMAPSS file, for generation in chunks.

    Use as a context manager. Each :meth:`append` adds rows to one split. Without
    ``sizes`` the datasets are resizable (chunked HDF5 storage, the only way HDF5 can
    grow a dataset; readers see the same arrays as in a contiguous file). With ``sizes``
    they are contiguous and uncompressed, as in NASA's files, and the appends must fill
    exactly that many rows. The file appears at ``path`` only when the block exits
    without an exception; otherwise the temporary file is deleted and any previous file
    at ``path`` is left untouched.

    Example::

        with NCMAPSSWriter("out.h5", attrs={"config": cfg_dict}) as writer:
            for chunk in chunks:
                writer.append("dev", chunk)

    Args:
        path: destination file; its directory must exist.
        attrs: extra root attributes (str / numbers / arrays; dicts and lists are
            stored as JSON strings). ``sample_rate_hz`` is written from the records.
        chunk_rows: HDF5 chunk length of resizable datasets.
        sizes: optional ``{"dev": N_dev, "test": N_test}`` final row counts.
    """

    def __init__(self, path, *, attrs=None, chunk_rows=_CHUNK_ROWS, sizes=None):
        self.path = os.fspath(path)
        self._attrs = _check_attrs(attrs)
        if int(chunk_rows) < 1:
            raise ValueError(f"chunk_rows must be >= 1, got {chunk_rows}")
        self._chunk_rows = int(chunk_rows)
        if sizes is not None and (
            set(sizes) != set(SPLITS) or any(int(v) < 0 for v in sizes.values())
        ):
            raise ValueError(
                f"sizes must map 'dev' and 'test' to row counts, got {sizes}"
            )
        self._sizes = None if sizes is None else {k: int(v) for k, v in sizes.items()}
        self._rows = dict.fromkeys(SPLITS, 0)
        self._tmp: str | None = None
        self._file: h5py.File | None = None
        self._rate: float | None = None

    def __enter__(self) -> NCMAPSSWriter:
        directory = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(directory):
            raise FileNotFoundError(f"output directory does not exist: {directory}")
        prefix = f".{os.path.basename(self.path)}."
        fd, self._tmp = tempfile.mkstemp(dir=directory, prefix=prefix, suffix=".tmp")
        os.close(fd)
        try:
            self._file = h5py.File(self._tmp, "w")
            for split, group in itertools.product(SPLITS, _GROUPS):
                k = _width(group)
                if self._sizes is None:
                    kwargs = {"maxshape": (None, k), "chunks": (self._chunk_rows, k)}
                    shape = (0, k)
                else:
                    kwargs, shape = {}, (self._sizes[split], k)
                dtype = _dtype(group)
                self._file.create_dataset(f"{group}_{split}", shape, dtype, **kwargs)
        except BaseException:
            self._discard()
            raise
        return self

    def append(self, split: str, record: Record) -> None:
        """Append the rows of ``record`` to ``split``, in row blocks.

        Args:
            split: ``"dev"`` or ``"test"``.
            record: rows to add; needs the 28 N-CMAPSS sensors and ``theta``. Its
                ``sample_rate_hz`` must equal that of earlier appends.
        """
        if self._file is None:
            raise ValueError("NCMAPSSWriter.append called outside its `with` block")
        _check_split(split)
        _check_layout(record, split)
        if self._rate is None:
            self._rate = record.sample_rate_hz
        elif not _same_rate(self._rate, record.sample_rate_hz):
            raise ValueError(
                f"record sample_rate_hz={record.sample_rate_hz} differs from the "
                f"{self._rate} of earlier records; one file has one rate"
            )
        offset, n = self._rows[split], record.num_rows
        if self._sizes is None:
            for group in _GROUPS:
                self._file[f"{group}_{split}"].resize(offset + n, axis=0)
        elif offset + n > self._sizes[split]:
            raise ValueError(f"{split}: more rows than sizes[{split!r}]")
        for a in range(0, n, _BLOCK_ROWS):
            b = min(n, a + _BLOCK_ROWS)
            arrays = _layout_arrays(record.take(slice(a, b)))
            for group in _GROUPS:
                self._file[f"{group}_{split}"][offset + a : offset + b] = arrays[group]
        self._rows[split] = offset + n

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            self._discard()
            return False
        try:
            if self._sizes is not None and self._rows != self._sizes:
                raise ValueError(f"rows written {self._rows} != sizes {self._sizes}")
            f = self._file
            for group, names in LAYOUT_NAMES.items():  # |S<max len>, as NASA's files
                f.create_dataset(f"{group}_var", data=np.array(names, dtype="S"))
            for key, value in self._attrs.items():
                f.attrs[key] = value
            if self._rate is not None:
                f.attrs["sample_rate_hz"] = self._rate
            f.close()
            with open(self._tmp, "rb") as handle:
                os.fsync(handle.fileno())
            # mkstemp creates mode 0600; a data file gets the usual umask permissions.
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(self._tmp, 0o666 & ~umask)
            os.replace(self._tmp, self.path)
        except BaseException:
            self._discard()
            raise
        self._file = None
        return False

    def _discard(self) -> None:
        if self._file is not None and self._file.id.valid:
            self._file.close()
        if self._tmp is not None and os.path.exists(self._tmp):
            os.unlink(self._tmp)
        self._file = None


def write_ncmapss(path, dev: Record, test: Record, *, attrs=None) -> None:
    """Write ``dev`` and ``test`` to ``path`` in the exact N-CMAPSS layout, atomically.

    Datasets are contiguous and uncompressed, as in the real files, and written in row
    blocks so that memory stays bounded. Sensor columns outside the 28 N-CMAPSS sensors
    and ``Record.extras`` have no place in the layout and are not written.

    Args:
        path: destination file; its directory must exist.
        dev: the development split (needs the 14 measured + 14 virtual sensors and
            theta).
        test: the test split (same requirements, same ``sample_rate_hz``).
        attrs: extra root attributes, as for :class:`NCMAPSSWriter`.
    """
    for split, record in (("dev", dev), ("test", test)):
        _check_layout(record, split)  # fail before any file is created
    sizes = {"dev": dev.num_rows, "test": test.num_rows}
    with NCMAPSSWriter(path, attrs=attrs, sizes=sizes) as writer:
        writer.append("dev", dev)
        writer.append("test", test)


# --------------------------------------------------------------------------- reading


def _open_read(path) -> tuple[str, h5py.File]:
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"N-CMAPSS file not found: {path}")
    try:
        return path, h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"{path} is not a readable HDF5 file: {err}") from err


def _dataset(f: h5py.File, path: str, key: str) -> h5py.Dataset:
    if key not in f:
        raise ValueError(
            f"{path}: missing dataset {key!r}; an N-CMAPSS file holds "
            f"{[f'{g}_{s}' for s in SPLITS for g in _GROUPS]} and "
            f"{[f'{g}_var' for g in LAYOUT_NAMES]}"
        )
    return f[key]


def _var_names(f: h5py.File, path: str, group: str) -> list[str]:
    """Decoded ``<group>_var`` column names (fixed-width bytes in the real files)."""
    raw = np.asarray(_dataset(f, path, f"{group}_var")[()]).ravel()
    return [
        (v.decode("ascii") if isinstance(v, bytes) else str(v)).strip() for v in raw
    ]


def _split_layout(f: h5py.File, path: str, split: str) -> dict:
    """Datasets and column names of ``split``, with the layout checked."""
    _check_split(split)
    dsets = {g: _dataset(f, path, f"{g}_{split}") for g in _GROUPS}
    names = {g: _var_names(f, path, g) for g in LAYOUT_NAMES}
    num_rows = dsets["A"].shape[0]
    for group, dset in dsets.items():
        k = 1 if group == "Y" else len(names[group])
        if dset.ndim != 2 or dset.shape != (num_rows, k):
            raise ValueError(
                f"{path}: dataset {group}_{split} has shape {dset.shape}, expected "
                f"({num_rows}, {k}) from A_{split} and {group}_var"
            )
    for group, required in (
        ("W", CONDITION_NAMES),
        ("T", HEALTH_NAMES),
        ("A", AUX_NAMES),
    ):
        missing = [n for n in required if n not in names[group]]
        if missing:
            raise ValueError(
                f"{path}: {group}_var lacks column(s) {missing}; has {names[group]}"
            )
    return {"dsets": dsets, "names": names, "num_rows": num_rows}


def _unit_ranges(a_dset, unit_col, wanted, start, stop, block_rows):
    """Maximal ``[a, b)`` row ranges whose unit is in ``wanted``, and all units seen.

    Only column ``unit_col`` of ``A`` is read, ``block_rows`` rows at a time.
    """
    ranges: list[list[int]] = []
    seen: set[int] = set()
    for a0 in range(start, stop, block_rows):
        units = a_dset[a0 : min(stop, a0 + block_rows), unit_col]
        seen.update(int(u) for u in np.unique(units))
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


def load_ncmapss(
    path,
    split: str = "dev",
    units=None,
    sensors=None,
    rows: tuple[int, int] | None = None,
    stride: int = 1,
    *,
    block_rows: int = _BLOCK_ROWS,
) -> Record:
    """Load (part of) one split of an N-CMAPSS file, ours or NASA's.

    Args:
        path: the ``.h5`` file.
        split: ``"dev"`` or ``"test"``.
        units: unit ids to keep (``None``: all). Rows come back in file order.
        sensors: sensor names of ``X_s_var`` / ``X_v_var`` to load, in this order
            (``None``: all of them, in :data:`SENSOR_NAMES` order; file columns whose
            name jaxcal does not know go to ``Record.extras``).
        rows: ``(start, stop)`` window of file rows to consider (``None``: all).
        stride: keep file rows ``start, start + stride, ...`` (aligned to the window
            start, so a unit selection sees exactly the rows the full load would).
        block_rows: rows per read block (bounds memory; small values only for tests).

    Returns:
        A :class:`Record` whose ``sample_rate_hz`` is the file's ``sample_rate_hz`` root
        attribute (1.0 when absent, as in NASA's files) divided by ``stride``.
    """
    if int(stride) != stride or stride < 1:
        raise ValueError(f"stride must be an integer >= 1, got {stride}")
    if int(block_rows) < 1:
        raise ValueError(f"block_rows must be >= 1, got {block_rows}")
    stride, block_rows = int(stride), int(block_rows)
    path, f = _open_read(path)
    with f:
        layout = _split_layout(f, path, split)
        dsets, names, num_rows = layout["dsets"], layout["names"], layout["num_rows"]
        start, stop = _row_window(rows, num_rows)
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
                    f"{path} [{split}] rows {start}:{stop} has no unit(s) {missing}; "
                    f"units there are {sorted(seen)}"
                )
        # Align every range to the global stride grid start, start + stride, ...
        ranges = [[a + (start - a) % stride, b] for a, b in ranges]
        ranges = [[a, b] for a, b in ranges if a < b]
        total = sum(len(range(a, b, stride)) for a, b in ranges)

        def read(group, cols):
            out = np.empty((total, len(cols)), dtype=_dtype(group))
            _read_into(dsets[group], ranges, stride, cols, out, block_rows)
            return out

        x_names, extra_names, plan = _sensor_plan(names, sensors, path)
        x = np.empty((total, len(x_names)), dtype=np.float64)
        extras = {}
        for group in ("X_s", "X_v"):
            picks = [(j, c) for j, (g, c) in enumerate(plan) if g == group]
            extra_picks = [(n, c) for n, (g, c) in extra_names if g == group]
            if not picks and not extra_picks:
                continue  # this group is not needed: do not touch it on disk
            cols = [c for _, c in picks] + [c for _, c in extra_picks]
            block = read(group, cols)
            x[:, [j for j, _ in picks]] = block[:, : len(picks)]
            for i, (name, _) in enumerate(extra_picks):
                extras[name] = block[:, len(picks) + i]
        aux = read("A", [names["A"].index(n) for n in AUX_NAMES])
        rate = float(f.attrs.get("sample_rate_hz", 1.0))
        return Record(
            w=read("W", [names["W"].index(n) for n in CONDITION_NAMES]),
            x=x,
            x_names=x_names,
            theta=read("T", [names["T"].index(n) for n in HEALTH_NAMES]),
            unit=aux[:, 0],
            cycle=aux[:, 1],
            flight_class=aux[:, 2],
            hs=aux[:, 3],
            rul=read("Y", [0])[:, 0],
            extras=extras,
            sample_rate_hz=rate / stride,
            source=f"{path}[{split}]",
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
    """Where requested sensors live: ``(x_names, extra columns, [(group, col)])``."""
    where = {}
    for group in ("X_s", "X_v"):
        for col, name in enumerate(names[group]):
            where.setdefault(name, (group, col))
    extra = []
    if sensors is None:
        x_names = tuple(n for n in SENSOR_NAMES if n in where)
        extra = [(n, where[n]) for n in where if n not in SENSOR_NAMES]
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
    return x_names, extra, [where[n] for n in x_names]


def ncmapss_info(path, *, block_rows: int = _BLOCK_ROWS) -> dict:
    """Summary of an N-CMAPSS file without loading its arrays.

    Args:
        path: the ``.h5`` file.
        block_rows: rows per block when scanning the unit column.

    Returns:
        ``{"path", "columns": {group: names}, "attrs": {...}, "sample_rate_hz",
        "splits": {split: {"rows": N, "units": [...]}}}``; a split appears when its
        ``A_<split>`` dataset exists.
    """
    path, f = _open_read(path)
    with f:
        columns = {g: _var_names(f, path, g) for g in LAYOUT_NAMES}
        splits = {}
        for split in SPLITS:
            if f"A_{split}" not in f:
                continue
            layout = _split_layout(f, path, split)
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
