"""Every source of calibration data becomes a :class:`~jaxcal.data.dataset.Dataset`.

:func:`read_dataset` takes a path (``.csv``, ``.parquet``, or a file the model reads
itself, :attr:`~jaxcal.model.Model.file_readers`: the turbofan's N-CMAPSS ``.h5`` /
``.hdf5`` and NASA C-MAPSS ``.txt``), a pandas DataFrame, numpy arrays through
:func:`dataset_from_arrays`, or a Dataset (returned as is).

Tables (CSV, Parquet, DataFrame) name their columns as the model names its
conditions and outputs; optional columns are ``unit`` (one stream per unit; default:
one unit), ``time`` (row order within a unit, unique in it; default: the file's
order), ``split`` (``train``/``val``/``test``, one per unit) and true-parameter
columns named as the model's parameters (for scoring only). Every other column is an
error that lists what was expected and what was found, unless it is renamed
(``rename={"T_in": "T_hot_in"}``) or ignored (``ignore=("comment",)``; an ignored
output, parameter, unit, time or split column is not read, a condition cannot be
ignored). A DataFrame's index levels named like these columns (``set_index(["unit",
"time"])``) are read as columns; a MultiIndex with other levels is an error. A column
name given twice (or made so by ``rename``), a table without rows, a time repeated
within a unit and a unit in two splits are errors naming them. Non-finite values
follow ``nonfinite``:
``"error"`` (default) names the file, each column, its first rows and the count;
``"drop"`` drops the rows and records ``{column: rows}`` in ``Dataset.dropped``.

Partial rows: a row with some outputs missing (NaN or an empty cell) while its
conditions, its other outputs and its true parameters are finite is kept with its
NaNs whatever ``nonfinite`` says (``Dataset.partial`` marks it; the calibrators use
or skip it, :mod:`jaxcal.calibrators.guard`). ``partial=False`` treats it as any
other non-finite row (training a policy needs complete rows).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from jaxcal.data.dataset import Dataset, partial_rows
from jaxcal.data.table_checks import (
    apply_nonfinite_policy,
    check_ignore,
    check_model_columns,
    check_unique_times,
    check_units_in_one_split,
    index_as_columns,
    numeric_columns,
    read_csv_table,
    renamed_columns,
    unit_and_time,
)
from jaxcal.model import Model
from jaxcal.model_spec import TABLE_COLUMNS as SPECIAL_COLUMNS


def dataset_from_frame(
    frame,
    model: Model,
    *,
    source: str = "DataFrame",
    rename: Mapping[str, str] | None = None,
    ignore: Sequence[str] = (),
    nonfinite: str = "error",
    row_offset: int = 0,
    partial: bool = True,
) -> Dataset:
    """A DataFrame whose columns are named as ``model``'s variables -> Dataset."""
    known = {
        *model.condition_names, *model.output_names, *model.parameter_names,
        *SPECIAL_COLUMNS,
    }  # fmt: skip
    rename = dict(rename or {})
    frame = index_as_columns(frame, known | set(rename), source)
    frame = renamed_columns(frame, rename, source)
    check_ignore(ignore, model, source)
    frame = frame.drop(columns=[c for c in frame.columns if str(c) in ignore])
    columns = [str(c) for c in frame.columns]
    outputs = check_model_columns(columns, model, known, source)
    if not len(frame):
        raise ValueError(f"no rows in {source} (columns {columns})")
    thetas = [n for n in model.parameter_names if n in columns]
    numeric = numeric_columns(
        frame, [*model.condition_names, *outputs, *thetas], source
    )
    keep, dropped = apply_nonfinite_policy(
        _partial_rows_exempt(numeric, outputs) if partial else numeric, nonfinite,
        source=source, row_of=lambda pos: pos + row_offset,
        row_word="line" if row_offset else "row",
    )  # fmt: skip
    unit, time = unit_and_time(frame, source, row_offset)
    split = frame["split"].to_numpy().astype(str) if "split" in columns else None
    data = Dataset(
        w=np.stack([numeric[n] for n in model.condition_names], axis=1),
        x=np.stack([numeric[n] for n in outputs], axis=1),
        condition_names=model.condition_names,
        output_names=tuple(outputs),
        unit=unit,
        time=time,
        theta=np.stack([numeric[n] for n in thetas], axis=1) if thetas else None,
        theta_names=tuple(thetas),
        split=split,
        source=source,
    )
    if dropped:
        data = data.take(keep)
        object.__setattr__(data, "dropped", dropped)
        if not data.num_rows:
            raise ValueError(f"{source}: every row has a non-finite value {dropped}")
    if "time" in columns:  # the default time (the row number) cannot repeat
        check_unique_times(data.unit, data.time, source)
    if split is not None:
        check_units_in_one_split(data.unit, data.split, source)
    return data


def _partial_rows_exempt(numeric: dict, outputs: Sequence[str]) -> dict:
    """``numeric`` with the missing outputs of partial rows filled (the non-finite
    policy then leaves those rows alone; the Dataset keeps their NaNs)."""
    x = np.stack([numeric[n] for n in outputs], axis=1)
    others = [v for n, v in numeric.items() if n not in outputs]
    others_finite = np.all([np.isfinite(v) for v in others], axis=0) if others else True
    exempt = partial_rows(x) & others_finite
    return {
        n: np.where(exempt, 0.0, v) if n in outputs else v for n, v in numeric.items()
    }


def dataset_from_arrays(
    w, x, model: Model, *, outputs: Sequence[str] | None = None, unit=None, time=None,
    theta=None, split=None,
) -> Dataset:  # fmt: skip
    """numpy arrays ``w [N, W]`` (the model's condition order) and ``x [N, S]``
    (``outputs``, default all of the model's) -> Dataset."""
    outputs = tuple(outputs) if outputs else model.output_names
    w = np.asarray(w, np.float64)
    n = w.shape[0] if w.ndim == 2 else 0
    if w.ndim == 2 and n == 0:
        raise ValueError("no rows in arrays (w has shape (0, ...))")
    data = Dataset(
        w=w,
        x=x,
        condition_names=model.condition_names,
        output_names=outputs,
        unit=np.zeros(n, np.int64) if unit is None else unit,
        time=np.arange(n) if time is None else time,
        theta=theta,
        theta_names=model.parameter_names if theta is not None else (),
        split=split,
    )
    if time is not None:
        check_unique_times(data.unit, data.time, data.source)
    if split is not None:
        check_units_in_one_split(data.unit, data.split, data.source)
    return data


def read_dataset(
    source,
    model: Model | None = None,
    *,
    rename: Mapping[str, str] | None = None,
    ignore: Sequence[str] = (),
    nonfinite: str = "error",
    partial: bool = True,
    **reader_options,
) -> Dataset:
    """Any supported source -> :class:`Dataset` (see the module docstring).

    Args:
        source: a path, a pandas DataFrame or a Dataset.
        model: the model whose names the columns follow (needed for tables and
            for the model's own files).
        rename: see the module docstring.
        ignore: see the module docstring.
        nonfinite: see the module docstring.
        partial: keep the partial rows of a table (module docstring); the
            N-CMAPSS and C-MAPSS readers apply ``nonfinite`` to every row.
        reader_options: passed to the model's own reader (the turbofan's N-CMAPSS
            reader: ``units``, ``sensors``, ``stride``; its C-MAPSS text reader).

    Raises:
        ValueError: unknown file type, unreadable file, column mismatch or
            non-finite values (naming file, column and rows).
    """
    if isinstance(source, Dataset):
        return source
    if model is not None and not isinstance(model, Model):
        load = f": jaxcal.models.load({model!r})" if isinstance(model, str) else ""
        raise ValueError(
            f"model: got {type(model).__name__} {model!r}; read_dataset needs a "
            f"jaxcal.Model{load}"
        )
    if hasattr(source, "columns") and hasattr(source, "to_numpy"):
        if model is None:
            raise ValueError("reading a DataFrame needs the model its columns follow")
        return dataset_from_frame(
            source, model, rename=rename, ignore=ignore, nonfinite=nonfinite,
            partial=partial,
        )  # fmt: skip
    if not isinstance(source, (str, os.PathLike)):
        raise ValueError(
            f"data: got a value of type {type(source).__name__}; expected a file "
            "path (str or "
            "pathlib.Path: .csv, .parquet, .h5/.hdf5, .txt), a pandas DataFrame or a "
            "jaxcal.Dataset (numpy arrays: "
            "jaxcal.data.readers.dataset_from_arrays(w, x, model))"
        )
    path = os.fspath(source)
    if not os.path.isfile(path):
        raise ValueError(f"data file not found: {path}")
    return _read_file(
        path, model, rename=rename, ignore=ignore, nonfinite=nonfinite,
        partial=partial, reader_options=reader_options,
    )  # fmt: skip


def _read_file(
    path: str, model: Model | None, *, rename, ignore, nonfinite: str,
    partial: bool, reader_options: dict,
) -> Dataset:  # fmt: skip
    """A data file -> Dataset, the reader picked by the extension (the options as
    in :func:`read_dataset`)."""
    ext = os.path.splitext(path)[1].lower()
    if ext in (".csv", ".parquet", ".pq"):
        if model is None:
            raise ValueError(f"{path}: reading a table needs the model it follows")
        try:
            frame = read_csv_table(path) if ext == ".csv" else pd.read_parquet(path)
        except ValueError as err:
            if str(err).startswith(path):  # ours: it names the file already
                raise
            raise ValueError(f"{path}: not a readable {ext[1:]} file ({err})") from None
        except Exception as err:  # noqa: BLE001 - any parser failure is bad input
            raise ValueError(f"{path}: not a readable {ext[1:]} file ({err})") from None
        return dataset_from_frame(
            frame, model, source=path, rename=rename, ignore=ignore,
            nonfinite=nonfinite, row_offset=2 if ext == ".csv" else 0,
            partial=partial,
        )  # fmt: skip
    readers = {} if model is None else model.file_readers
    if ext in readers:  # the model's own files (the turbofan's N-CMAPSS, C-MAPSS)
        return readers[ext](path, nonfinite=nonfinite, rename=rename, **reader_options)
    own = f" or {model.name}'s own {', '.join(sorted(readers))}" if readers else ""
    raise ValueError(
        f"{path}: unknown data file type {ext!r}; expected .csv, .parquet{own}"
        + (
            " (a model's own files, as the turbofan's N-CMAPSS .h5/.hdf5 and C-MAPSS "
            ".txt, are read with the model: read_dataset(path, model))"
            if model is None
            else ""
        )
    )
