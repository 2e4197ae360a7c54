"""Reader of the NASA C-MAPSS (Saxena et al., PHM08) 26-column text files.

Each line of ``train_FD00x.txt`` / ``test_FD00x.txt`` holds ``unit cycle op1 op2 op3 s1
.. s21`` (space separated, data_facts.md §1.1). The reader returns the same
:class:`~jaxcal.models.turbofan.data.record.Record` as the N-CMAPSS HDF5 reader, so
calibration code can run on real NASA data: ``w = (1000 op1 [ft], op2 [Mach], op3 [TRA
%], s1 [T2 degR])`` (data_facts.md §1.3), the sensors whose units really match an
N-CMAPSS / C-MAPSS name go to ``x`` under that name, and the rest go to ``extras``:
``s11`` is labelled Ps30 but reads about 47 where P30 reads 553 psia, ``s12`` (phi) is
not in pps/psi and ``s17`` (htBleed) has no N-CMAPSS name (data_facts.md §1.2). The raw
op settings are kept in ``extras`` too.

C-MAPSS has one snapshot per flight, so ``sample_rate_hz`` is NaN (no within-flight time
base), and it has no health ground truth (``theta=None``), flight class or ``hs`` (NaN).

A bad line is an error naming the file, the line and (for a bad token) the column; a
``nan`` / ``inf`` token follows the ``nonfinite`` policy of
:data:`~jaxcal.data.table_checks.NONFINITE_POLICIES` (default: refuse), except in the
unit and cycle columns, where it is always an error.
"""

from __future__ import annotations

import os

import numpy as np

from jaxcal.data.table_checks import apply_nonfinite_policy, check_nonfinite_policy
from jaxcal.models.turbofan.data.record import Record

NUM_COLUMNS = 26
# C-MAPSS sensor number -> jaxcal sensor name, only where the units truly correspond.
SENSOR_MAP: dict[int, str] = {
    2: "T24",
    3: "T30",
    4: "T50",
    5: "P2",
    6: "P15",
    7: "P30",
    8: "Nf",
    9: "Nc",
    10: "epr",
    13: "NRf",
    14: "NRc",
    15: "BPR",
    16: "farB",
    18: "Nf_dmd",
    19: "PCNfR_dmd",
    20: "W31",
    21: "W32",
}
# C-MAPSS sensor number -> extras key, for outputs with no matching N-CMAPSS quantity.
EXTRA_MAP: dict[int, str] = {11: "Ps30_cmapss", 12: "phi_cmapss", 17: "htBleed"}
FT_PER_KFT = 1000.0
# The 26 columns of a line, as the NASA readme names them.
COLUMN_NAMES: tuple[str, ...] = ("unit", "cycle", "op1", "op2", "op3") + tuple(
    f"s{s}" for s in range(1, 22)
)


def column_label(j: int) -> str:
    """Column ``j`` (0-based) as named in messages: ``s3 (T30)``, ``op1``."""
    name = COLUMN_NAMES[j]
    if j < 5:
        return name
    s = j - 4
    known = {1: "T2", **SENSOR_MAP, **EXTRA_MAP}.get(s)
    return f"{name} ({known})" if known else name


def _parse(path: str) -> tuple[np.ndarray, np.ndarray]:
    """The numeric table ``[N, 26]`` and the 1-based file line number of each row."""
    rows, line_numbers = [], []
    with open(path, encoding="ascii", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            fields = line.split()
            if not fields:
                continue  # blank lines carry nothing; the NASA files have none
            if len(fields) != NUM_COLUMNS:
                raise ValueError(
                    f"{path}:{number}: expected {NUM_COLUMNS} columns (unit, cycle, "
                    f"op1..op3, s1..s21), got {len(fields)}"
                )
            try:
                rows.append([float(v) for v in fields])
            except ValueError:
                j = next(j for j, v in enumerate(fields) if not _is_number(v))
                raise ValueError(
                    f"{path}:{number}: non-numeric value {fields[j]!r} in column "
                    f"{j + 1} ({column_label(j)})"
                ) from None
            line_numbers.append(number)
    if not rows:
        raise ValueError(f"{path}: no data lines")
    return np.asarray(rows, dtype=np.float64), np.asarray(line_numbers)


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _check_ids(path: str, table: np.ndarray, lines: np.ndarray) -> None:
    """Integer unit / cycle, each unit in one block, cycles contiguous within a unit."""
    for col, name in ((0, "unit"), (1, "cycle")):
        values = table[:, col]
        # not (>= 1) is also True for NaN: a row without unit or cycle is no row.
        bad = (values != np.round(values)) | ~(values >= 1)
        if bad.any():
            raise ValueError(
                f"{path}:{lines[bad][0]}: {name} must be an integer >= 1, "
                f"got {values[bad][0]}"
            )
    unit, cycle = table[:, 0], table[:, 1]
    new_unit = np.concatenate([[True], unit[1:] != unit[:-1]])
    starts = unit[new_unit]
    repeated = np.ones(len(starts), dtype=bool)
    repeated[np.unique(starts, return_index=True)[1]] = False  # first blocks are fine
    if repeated.any():
        i = np.flatnonzero(new_unit)[np.flatnonzero(repeated)[0]]
        raise ValueError(
            f"{path}:{lines[i]}: unit {int(unit[i])} reappears after other units; "
            "each unit's rows must be contiguous"
        )
    broken = ~new_unit & (cycle != np.concatenate([[np.nan], cycle[:-1] + 1]))
    if broken.any():
        i = np.flatnonzero(broken)[0]
        raise ValueError(
            f"{path}:{lines[i]}: cycle {int(cycle[i])} of unit {int(unit[i])} does not "
            f"follow cycle {int(cycle[i - 1])}; cycles must be contiguous"
        )


def _read_rul(rul_path: str, num_units: int) -> np.ndarray:
    """One integer per test unit, line ``u`` for unit ``u``."""
    if not os.path.isfile(rul_path):
        raise FileNotFoundError(f"C-MAPSS RUL file not found: {rul_path}")
    values = []
    with open(rul_path, encoding="ascii", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            fields = line.split()
            if not fields:
                continue
            if len(fields) != 1 or not fields[0].isdigit():
                raise ValueError(
                    f"{rul_path}:{number}: expected one non-negative integer, "
                    f"got {line!r}"
                )
            values.append(int(fields[0]))
    if len(values) != num_units:
        raise ValueError(
            f"{rul_path} has {len(values)} RUL values but the test file has "
            f"{num_units} units"
        )
    return np.asarray(values, dtype=np.int64)


def _is_test_file(path: str, rul_path, kind: str) -> bool:
    """Whether ``path`` holds truncated test series (see ``kind`` of
    :func:`load_cmapss_text`)."""
    if kind not in ("auto", "train", "test"):
        raise ValueError(f"kind must be 'auto', 'train' or 'test', got {kind!r}")
    if kind == "auto":
        is_test = rul_path is not None or os.path.basename(path).startswith("test")
    else:
        is_test = kind == "test"
    if rul_path is not None and not is_test:
        raise ValueError("rul_path is only meaningful for a test file (kind='test')")
    return is_test


def _remaining_useful_life(path: str, unit, cycle, is_test: bool, rul_path):
    """[N] RUL of every line: the unit's last cycle - cycle (train), plus the RUL
    file's value of the unit (test), -1 when a test file comes without one."""
    units, inverse = np.unique(unit, return_inverse=True)
    last_per_unit = np.zeros(len(units), dtype=np.int64)
    np.maximum.at(last_per_unit, inverse, cycle)
    last_cycle = last_per_unit[inverse]
    if not is_test:
        return last_cycle - cycle
    if rul_path is None:
        return np.full_like(cycle, -1)  # a truncated series with unknown failure time
    rul_values = _read_rul(os.fspath(rul_path), len(units))
    if units[0] != 1 or units[-1] != len(units):
        raise ValueError(
            f"{path}: test units must be 1..{len(units)} to match {rul_path} "
            f"line by line, got {units.tolist()[:5]}..."
        )
    return rul_values[unit - 1] + last_cycle - cycle


def load_cmapss_text(
    path, rul_path=None, *, kind: str = "auto", nonfinite: str = "error"
) -> Record:
    """Load one NASA C-MAPSS text file into a :class:`Record`.

    Args:
        path: ``train_FD00x.txt`` or ``test_FD00x.txt``.
        rul_path: the matching ``RUL_FD00x.txt`` for a test file (one integer per unit,
            line ``u`` for unit ``u``).
        kind: ``"train"`` (run to failure), ``"test"`` (truncated series) or ``"auto"``:
            test when ``rul_path`` is given or the file name starts with ``test``.
        nonfinite: lines with ``nan`` / ``inf`` values: ``"error"`` refuses them
            (ValueError naming the file, each column, its first lines and count),
            ``"drop"`` drops them (``Record.dropped`` counts them per column; the RUL
            still counts from the unit's last cycle in the file), ``"keep"`` keeps
            them.

    Returns:
        A Record with ``w [N, 4]`` (alt ft, Mach, TRA %, T2 degR), ``x [N, 17]``
        named by :data:`SENSOR_MAP`, extras ``Ps30_cmapss``, ``phi_cmapss``,
        ``htBleed``, ``op1_kft``, ``op2``, ``op3``, and ``rul`` = last cycle of the
        unit - cycle for a train file, RUL_file[unit] + last cycle - cycle for a test
        file with ``rul_path``, and -1 (unknown) for a test file without it.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"C-MAPSS text file not found: {path}")
    is_test = _is_test_file(path, rul_path, kind)
    check_nonfinite_policy(nonfinite)

    table, lines = _parse(path)
    _check_ids(path, table, lines)
    keep, dropped = apply_nonfinite_policy(
        {column_label(j): table[:, j] for j in range(2, NUM_COLUMNS)},
        nonfinite,
        source=path,
        row_of=lambda pos: lines[pos],
        row_word="line",
    )
    if keep is not None and not keep.any():
        raise ValueError(f"{path}: every line holds a NaN or Inf value: {dropped}")
    # Ids and RUL come from every line (a dropped last line must not shift the RUL);
    # the rows are dropped at the end.
    unit = table[:, 0].astype(np.int64)
    cycle = table[:, 1].astype(np.int64)
    rul = _remaining_useful_life(path, unit, cycle, is_test, rul_path)
    if keep is not None:
        table, unit, cycle, rul = table[keep], unit[keep], cycle[keep], rul[keep]
    sensor = {s: table[:, 4 + s] for s in range(1, 22)}  # s1 is 0-based column 5
    w = np.stack(
        [table[:, 2] * FT_PER_KFT, table[:, 3], table[:, 4], sensor[1]], axis=1
    )
    extras = {name: sensor[s] for s, name in EXTRA_MAP.items()}
    extras.update(op1_kft=table[:, 2], op2=table[:, 3], op3=table[:, 4])
    nan = np.full(len(unit), np.nan)
    return Record(
        w=w,
        x=np.stack([sensor[s] for s in SENSOR_MAP], axis=1),
        x_names=tuple(SENSOR_MAP.values()),
        theta=None,
        unit=unit,
        cycle=cycle,
        flight_class=nan,
        hs=nan.copy(),
        rul=rul,
        extras=extras,
        sample_rate_hz=float("nan"),
        source=f"cmapss:{path}",
        dropped=dropped,
        dropped_rows=0 if keep is None else int(keep.size - keep.sum()),
    )
