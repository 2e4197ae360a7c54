"""Atomic writers of the N-CMAPSS HDF5 layout (one-shot and appendable).

Writers fill a temporary file in the destination directory and ``os.replace`` it into
place only when everything succeeded (layout:
:mod:`jaxcal.models.turbofan.data.ncmapss_io`). The temporary file is made by the
project's atomic writer (:func:`jaxcal.runs.atomic.make_temp`), so a file left by a
writer killed mid-way is removed by the next write to the same path.
"""

from __future__ import annotations

import itertools
import os

import h5py
import numpy as np

from jaxcal.models.turbofan.data.ncmapss_layout import (
    _BLOCK_ROWS,
    _CHUNK_ROWS,
    _GROUPS,
    LAYOUT_NAMES,
    SPLITS,
    _check_attrs,
    _check_layout,
    _check_split,
    _dtype,
    _layout_arrays,
    _same_rate,
    _width,
)
from jaxcal.models.turbofan.data.record import Record
from jaxcal.runs.atomic import make_temp, release_temp


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
        fd, self._tmp = make_temp(self.path)  # removes temps of killed writers first
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
        release_temp(self._tmp)
        self._file = None
        return False

    def _discard(self) -> None:
        if self._file is not None and self._file.id.valid:
            self._file.close()
        if self._tmp is not None:
            release_temp(self._tmp)
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
