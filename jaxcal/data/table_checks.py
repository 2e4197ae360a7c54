"""The checks a table passes before it becomes a :class:`~jaxcal.data.dataset.Dataset`
(:mod:`jaxcal.data.readers`): how a CSV's separator and decimal mark are read, how
its index, column names and ``ignore=`` are read,
that its columns fit the model and are numeric, its unit and time ids, and the two
facts about units that padding relies on (a time is not repeated within a unit; a
unit lies in one split), and what every reader (the turbofan's N-CMAPSS and C-MAPSS
readers too) does with non-finite rows (:data:`NONFINITE_POLICIES`). Each failure is
a ``ValueError`` naming the file or frame, the columns, units or times, and what to do.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from jaxcal.model import Model
from jaxcal.model_spec import TABLE_COLUMNS

# a number written with a decimal comma (``2,5``, ``-0,1e-3``): the European CSV
_DECIMAL_COMMA = re.compile(r"\s*[-+]?\d*,\d+([eE][-+]?\d+)?\s*")
# a number written with a decimal point, or an integer
_DECIMAL_POINT = re.compile(r"\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*")
INT64_MAX = np.iinfo(np.int64).max
EXACT_FLOAT = 2**53  # integers above this are not all exact in float64
# What a reader does with a row holding NaN / Inf in a column it returns.
# "error": refuse (ValueError naming file, columns, first rows, counts); "drop": drop
# the row and report it in Record.dropped; "keep": leave it for a caller that guards
# every sample itself (the streaming runners skip and flag such samples).
NONFINITE_POLICIES: tuple[str, ...] = ("error", "drop", "keep")
# Row numbers named per column in a non-finite error (the count covers the rest).
MAX_ROWS_NAMED = 5


def read_csv_table(path: str):
    """A CSV file as a DataFrame, ``,`` or ``;`` separated.

    A spreadsheet saved in a European locale separates by ``;`` and writes decimals
    with a comma (``2,5``); read with the default ``,`` it splits every number in
    two. The header decides, as it holds names, not numbers: a header with ``;``
    and no ``,`` is read with ``sep=";"``, and a column whose every value is a
    number with a decimal comma is read as those numbers (a column mixing ``2,5``
    and ``2.5`` is an error naming it). A header with both is an error saying so.
    """
    with open(path, encoding="utf-8", errors="replace") as f:
        header = f.readline()
    if ";" not in header:
        return pd.read_csv(path)
    if "," in header:
        raise ValueError(
            f"{path}: the header line holds both ';' and ',' ({header.strip()[:80]!r}"
            "), so the separator is ambiguous; save the file with one separator "
            "(',' with '.' decimals, or ';' with ',' decimals)"
        )
    frame = pd.read_csv(path, sep=";", dtype=str)
    for name in frame.columns:
        frame[name] = _number_column(frame[name], str(name), path)
    return frame


def _number_column(values, name: str, path: str):
    """A ``;``-separated file's text column as numbers (decimal comma or point), or
    as text when it is not numbers (a ``split`` column)."""
    text = values.dropna().astype(str)
    comma = text.str.fullmatch(_DECIMAL_COMMA.pattern)
    point = text.str.fullmatch(_DECIMAL_POINT.pattern)
    if len(text) and (comma | point).all():
        if comma.any() and text.str.contains(r"\.", regex=True).any():
            rows = (np.flatnonzero(comma.to_numpy())[:3] + 2).tolist()
            raise ValueError(
                f"{path}: column {name!r} mixes decimal commas (lines {rows}) and "
                "decimal points; write every number of a column the same way"
            )
        return pd.to_numeric(values.str.replace(",", ".", regex=False))
    return values


def index_as_columns(frame, names: set, source: str):
    """Index levels named like a column the reader knows (``unit``, ``time``, a
    condition, ... or a ``rename`` key) moved into the columns; a MultiIndex
    groups rows in a way the reader cannot guess otherwise, so one with another
    level is an error. A single unnamed or otherwise named index is not read (the
    rows' order is the frame's)."""
    levels = list(frame.index.names)
    used = [n for n in levels if n is not None and str(n) in names]
    if frame.index.nlevels > 1 and len(used) < len(levels):
        raise ValueError(
            f"{source}: the DataFrame's index has levels {levels}; only levels "
            f"named like the columns it reads ({sorted(TABLE_COLUMNS)}, the model's "
            "conditions, outputs and parameters, or a rename= key) can be read: name "
            "the levels (e.g. unit, time) or reset_index() and map them with rename="
        )
    # set_index(..., drop=False) keeps the column: the same values twice are fine
    same = [
        n
        for n in used
        if n in frame.columns
        and np.array_equal(frame.index.get_level_values(n), frame[n].to_numpy())
    ]
    used = [n for n in used if n not in same]
    clash = [n for n in used if n in frame.columns]
    if clash:
        raise ValueError(
            f"{source}: {clash} is both an index level and a column of the "
            "DataFrame; drop one of them"
        )
    return frame.reset_index(level=used) if used else frame


def renamed_columns(frame, rename: Mapping[str, str], source: str):
    """``frame`` with its columns renamed; two columns of one name (given so, or
    made so by ``rename``) are an error naming them."""
    before = [str(c) for c in frame.columns]
    after = [rename.get(c, c) for c in before]
    repeated = sorted({c for c in after if after.count(c) > 1})
    if repeated:
        name = repeated[0]
        sources = [b for b, a in zip(before, after, strict=True) if a == name]
        how = (
            f"columns {sources} are all renamed to {name!r} by rename="
            if any(b != name for b in sources)
            else f"{len(sources)} columns are named {name!r}"
        )
        raise ValueError(
            f"{source}: {how}; a column name must appear once (repeated: "
            f"{repeated}): drop or rename the extra column"
        )
    return frame.rename(columns=dict(zip(frame.columns, after, strict=True)))


def parse_rename(pairs: Sequence[str]) -> dict[str, str]:
    """``("T_24:T24", ...)`` (the ``dataset.rename`` form) as ``{"T_24": "T24"}``."""
    out = {}
    for pair in pairs:
        old, sep, new = pair.partition(":")
        if not sep or not old or not new or ":" in new:
            raise ValueError(
                f"rename entries must be <file name>:<jaxcal name>, got {pair!r}"
            )
        out[old.strip()] = new.strip()
    return out


def check_ignore(ignore: Sequence[str], model: Model, source: str) -> None:
    """``ignore=`` skips columns; a condition cannot be skipped (the model needs
    every one), an output, true parameter or ``unit``/``time``/``split`` column can
    (it is then not read)."""
    if isinstance(ignore, str):
        raise ValueError(f"ignore= takes a sequence of column names, got {ignore!r}")
    needed = [c for c in ignore if c in model.condition_names]
    if needed:
        raise ValueError(
            f"{source}: ignore={tuple(ignore)} names the condition(s) {needed}, which "
            f"model {model.name!r} needs (conditions {list(model.condition_names)})"
        )


def check_unique_times(unit: np.ndarray, time: np.ndarray, source: str) -> None:
    """A time given twice in one unit leaves its rows' order to chance (a row logged
    twice, or several rows per cycle): an error naming the units and times.

    Args:
        unit, time: ``[N]`` the rows' unit ids and times.
        source: the file or frame, for the message.
    """
    order = np.lexsort((time, unit))
    u, t = unit[order], time[order]
    twice = (u[1:] == u[:-1]) & (t[1:] == t[:-1])
    if not twice.any():
        return
    units = np.unique(u[1:][twice])
    shown = "; ".join(
        f"unit {uu}: time {np.unique(t[1:][twice & (u[1:] == uu)])[:5].tolist()}"
        for uu in units[:3].tolist()
    )
    raise ValueError(
        f"{source}: time repeats within a unit ({shown}"
        + ("; ..." if len(units) > 3 else "")
        + "), so the rows' order is unknown. Remove the repeated rows, or, if several "
        "rows per time step are meant, leave the time column out (ignore=('time',)) "
        "and give the rows in order"
    )


def check_units_in_one_split(unit: np.ndarray, split: np.ndarray, source: str) -> None:
    """A unit whose rows carry two split labels would put training rows into the
    test score: an error naming the units and their labels."""
    pairs = np.unique(np.stack([unit.astype(str), split.astype(str)], 1), axis=0)
    names, counts = np.unique(pairs[:, 0], return_counts=True)
    straddle = names[counts > 1]
    if len(straddle):
        labels = {u: sorted(pairs[pairs[:, 0] == u, 1].tolist()) for u in straddle[:3]}
        shown = "; ".join(f"unit {u}: {v}" for u, v in labels.items())
        raise ValueError(
            f"{source}: the split column changes inside a unit ({shown}"
            + ("; ..." if len(straddle) > 3 else "")
            + "); each unit must lie in one split (train, val or test), or its "
            "training rows would be scored as test rows"
        )


def check_model_columns(columns: list[str], model: Model, known: set, source: str):
    """Every column must be ``known``, every condition present and at least one
    output; the error lists what was expected and what was found.

    Returns:
        The model's outputs present, in the model's order.
    """
    unknown = [c for c in columns if c not in known]
    missing = [n for n in model.condition_names if n not in columns]
    outputs = [n for n in model.output_names if n in columns]
    if unknown or missing or not outputs:
        raise ValueError(
            f"{source}: columns do not match model {model.name!r}"
            + (f"; unknown columns {unknown}" if unknown else "")
            + (f"; missing conditions {missing}" if missing else "")
            + ("; no output column" if not outputs else "")
            + f". Expected conditions {list(model.condition_names)}, outputs (any "
            f"of) {list(model.output_names)}, optional {list(TABLE_COLUMNS)} and "
            f"true parameters {list(model.parameter_names)}; found {columns}. Map "
            "other names with rename={...} or skip columns with ignore=(...)"
        )
    return outputs


def numeric_columns(frame, names: Sequence[str], source: str) -> dict:
    """``{name: float64 [N] values}`` of the columns ``names``; a column that does
    not convert is an error naming it."""
    numeric = {}
    for name in names:
        try:
            numeric[name] = frame[name].to_numpy(dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(
                f"{source}: column {name!r} is not numeric ({err})"
            ) from None
    return numeric


def unit_and_time(frame, source: str, row_offset: int):
    """The ``unit`` and ``time`` columns (defaults: one unit, the row order); both
    must be numeric and finite (a row without its unit or time is no row).

    Args:
        row_offset: added to the 0-based row in messages (a CSV's header line).
    """
    n = len(frame)
    columns = [str(c) for c in frame.columns]
    unit = frame["unit"].to_numpy() if "unit" in columns else np.zeros(n, np.int64)
    unit = _unit_ids(unit, source, row_offset)
    time = frame["time"].to_numpy() if "time" in columns else np.arange(n)
    for name, values in (("unit", unit), ("time", time)):
        try:
            finite = np.isfinite(np.asarray(values, np.float64))
        except (TypeError, ValueError):
            raise ValueError(f"{source}: column {name!r} must be numeric") from None
        if not finite.all():
            row = int(np.flatnonzero(~finite)[0]) + row_offset
            raise ValueError(f"{source}: column {name!r} is empty or NaN at row {row}")
    return unit, time


def _unit_ids(unit: np.ndarray, source: str, row_offset: int) -> np.ndarray:
    """The unit ids as read, or an error where ``int64`` (the Dataset's unit type)
    cannot hold them apart: ids beyond its range (read as ``uint64`` or as Python
    integers) or integers written as floats beyond ``2**53`` would merge distinct
    units into one."""
    if unit.dtype.kind == "u":
        beyond = unit > INT64_MAX
    elif unit.dtype.kind == "O":
        ints = [_as_int(v) for v in unit]
        beyond = np.array([v is not None and abs(v) > INT64_MAX for v in ints], bool)
    elif unit.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            beyond = np.abs(unit) > EXACT_FLOAT
    else:
        return unit
    if beyond.any():
        rows = np.flatnonzero(beyond)
        first = ", ".join(str(int(r) + row_offset) for r in rows[:5])
        raise ValueError(
            f"{source}: column 'unit' holds ids too large to keep apart ({rows.size} "
            f"rows: {first}{', ...' if rows.size > 5 else ''}; e.g. {unit[rows[0]]}):"
            f" unit ids are int64 (at most {INT64_MAX}) and exact as floats only up "
            f"to 2**53, so distinct units would merge; map them to smaller ids"
        )
    return unit


def _as_int(value) -> int | None:
    """``value`` as a Python integer when it is one (or its digits), else None."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, str) and re.fullmatch(r"\s*[-+]?\d+\s*", value):
        return int(value)
    return None


def check_nonfinite_policy(policy: str) -> str:
    """``policy`` if it is one of :data:`NONFINITE_POLICIES`, else a clear error."""
    if policy not in NONFINITE_POLICIES:
        raise ValueError(
            f"nonfinite must be one of {list(NONFINITE_POLICIES)}, got {policy!r}"
        )
    return policy


def nonfinite_rows(
    columns: Mapping[str, np.ndarray],
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Rows holding a NaN or Inf, overall and per column.

    Args:
        columns: name -> ``[N]`` values; every column has the same ``N``.

    Returns:
        ``(bad [N] bool, {name: [k] sorted positions})``; the dict holds only the
        columns that have a non-finite value.
    """
    bad, where = None, {}
    for name, values in columns.items():
        finite = np.isfinite(values)
        bad = ~finite if bad is None else bad | ~finite
        if not finite.all():
            where[name] = np.flatnonzero(~finite)
    return (np.zeros(0, bool) if bad is None else bad), where


def nonfinite_message(
    where: Mapping[str, np.ndarray],
    num_bad: int,
    num_rows: int,
    *,
    source: str,
    row_of=None,
    row_word: str = "row",
) -> str:
    """The error of ``nonfinite="error"``: file, each column, first rows, counts.

    Args:
        where: column -> positions of its non-finite rows (:func:`nonfinite_rows`).
        num_bad: rows with any non-finite value; ``num_rows``: rows checked.
        source: the file (and split) named first in the message.
        row_of: positions -> row numbers as the user sees them in the file (line
            numbers of a text file, file rows of an HDF5 split); ``None``: positions.
        row_word: ``"row"`` or ``"line"``.
    """
    row_of = (lambda pos: pos) if row_of is None else row_of
    parts = []
    for name, pos in where.items():
        first = ", ".join(str(int(r)) for r in row_of(pos[:MAX_ROWS_NAMED]))
        more = ", ..." if pos.size > MAX_ROWS_NAMED else ""
        plural = "s" if pos.size > 1 else ""
        parts.append(
            f"column {name}: {pos.size} {row_word}{plural} ({row_word}{plural} "
            f"{first}{more})"
        )
    return (
        f"{source}: non-finite values (NaN or Inf) in {num_bad} of {num_rows} "
        f"{row_word}s; " + "; ".join(parts) + ". Fix the file, or drop these rows "
        "with nonfinite='drop' (train / evaluate: dataset.nonfinite=drop)"
    )


def apply_nonfinite_policy(
    columns: Mapping[str, np.ndarray],
    policy: str,
    *,
    source: str,
    row_of=None,
    row_word: str = "row",
) -> tuple[np.ndarray | None, dict[str, int]]:
    """What a reader does with the non-finite rows of the columns it returns.

    Args:
        columns: name -> ``[N]`` values the reader returns.
        policy: one of :data:`NONFINITE_POLICIES`.
        source, row_of, row_word: as for :func:`nonfinite_message`.

    Returns:
        ``(keep, dropped)``: ``keep`` is the ``[N]`` bool mask of rows to keep, or
        ``None`` when every row stays; ``dropped`` maps each column to its number of
        dropped rows (empty unless ``policy == "drop"`` found some).

    Raises:
        ValueError: ``policy == "error"`` and a value is NaN or Inf (the message names
            the file, each affected column, its first rows and its count).
    """
    check_nonfinite_policy(policy)
    if policy == "keep":
        return None, {}
    bad, where = nonfinite_rows(columns)
    if not where:
        return None, {}
    if policy == "error":
        raise ValueError(
            nonfinite_message(
                where,
                int(bad.sum()),
                int(bad.size),
                source=source,
                row_of=row_of,
                row_word=row_word,
            )
        )
    return ~bad, {name: int(pos.size) for name, pos in where.items()}
