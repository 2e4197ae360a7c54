"""The turbofan's files as :class:`~jaxcal.data.dataset.Dataset` s: :func:`read_file`
(N-CMAPSS ``.h5``/``.hdf5``, C-MAPSS ``.txt``) for :func:`jaxcal.data.readers.
read_dataset` (the turbofan model's ``file_readers``); one split of an N-CMAPSS file."""

import os

import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.data.padded import Padded
from jaxcal.models.turbofan.data.cmapss_text import load_cmapss_text
from jaxcal.models.turbofan.data.ncmapss_io import load_ncmapss, ncmapss_info
from jaxcal.models.turbofan.physics.constants import CONDITION_NAMES, HEALTH_NAMES


def dataset_from_record(record, split: str | None = None) -> Dataset:
    """An N-CMAPSS / C-MAPSS :class:`~jaxcal.models.turbofan.data.record.Record` ->
    Dataset."""
    n = record.num_rows
    return Dataset(
        w=record.w,
        x=record.x,
        condition_names=CONDITION_NAMES,
        output_names=tuple(record.x_names),
        unit=record.unit,
        time=record.cycle,
        theta=record.theta,
        theta_names=HEALTH_NAMES if record.theta is not None else (),
        split=None if split is None else np.full(n, split),
        source=record.source,
        dropped=record.dropped,
        dropped_rows=record.dropped_rows,
    )


def read_ncmapss_split(path, split: str, *, label: bool = True, **options) -> Dataset:
    """One split of an N-CMAPSS file as a Dataset (``label``: with its split column;
    ``options``: those of :func:`load_ncmapss`)."""
    record = load_ncmapss(path, split, **options)
    return dataset_from_record(record, split if label else None)


def read_ncmapss_padded(
    path, split: str, *, max_len: int | None = None, dtype=np.float64, **options
) -> Padded:
    """The units of one split of an N-CMAPSS file padded to ``max_len`` (``None``:
    the longest; a longer unit is an error): ascending ids, file order within a
    unit, flight numbers in ``cycle``, all ten health modifiers in ``theta``
    (:meth:`~jaxcal.models.turbofan.data.record.Record.padded`; ``options`` as for
    :func:`read_ncmapss_split`)."""
    return load_ncmapss(path, split, **options).padded(dtype, max_len)


def read_file(path: str, *, nonfinite: str, rename, **options) -> Dataset:
    """An N-CMAPSS file (``.h5``/``.hdf5``: its splits in one Dataset) or a NASA
    C-MAPSS text file (``.txt``) -> Dataset (``options``: :func:`load_ncmapss`'s or
    :func:`~jaxcal.models.turbofan.data.cmapss_text.load_cmapss_text`'s)."""
    if os.path.splitext(path)[1].lower() == ".txt":
        record = load_cmapss_text(path, nonfinite=nonfinite, **options)
        return dataset_from_record(record)
    splits = [s for s in ("dev", "test") if s in ncmapss_info(path)["splits"]]
    options = {"nonfinite": nonfinite, "rename": rename, **options}
    parts = [read_ncmapss_split(path, split, **options) for split in splits]
    first, source = parts[0], path
    cat = lambda f: np.concatenate([getattr(p, f) for p in parts])  # noqa: E731
    has_theta = all(p.theta is not None for p in parts)
    return Dataset(
        w=cat("w"),
        x=cat("x"),
        condition_names=first.condition_names,
        output_names=first.output_names,
        unit=cat("unit"),
        time=cat("time"),
        theta=cat("theta") if has_theta else None,
        theta_names=first.theta_names if has_theta else (),
        split=cat("split") if all(p.split is not None for p in parts) else None,
        source=source,
    )
