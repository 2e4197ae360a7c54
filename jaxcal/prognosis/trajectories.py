"""Calibrated health trajectories per unit, padded for ``vmap``: the prognosis's input.

A :class:`Trajectories` holds, per unit, the time of each used row and the calibrated
parameters there (``[U, T, P]`` with a validity mask), whichever method produced them.
:func:`from_result` reads a :class:`~jaxcal.calibrators.front.result.CalibrationResult`
(rows the calibrator skipped, and rows whose estimate is not finite, are masked);
:func:`from_arrays` takes plain per-row arrays, for trajectories from elsewhere.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

MIN_ROWS = 3  # a trend needs a few points; a unit with fewer is refused, named


@dataclasses.dataclass(frozen=True)
class Trajectories:
    """Per-unit parameter trajectories, padded to the longest unit.

    Attributes:
        unit: ``[U]`` unit ids, in first-appearance order of the rows.
        time: ``[U, T]`` each row's time (cycle); padding repeats the last time.
        theta: ``[U, T, P]`` the calibrated parameters; padding repeats the last row.
        std: ``[U, T, P]`` their std where the method gave one (else NaN).
        mask: ``[U, T]`` True on used rows.
        names: ``P`` parameter names.
    """

    unit: np.ndarray
    time: np.ndarray
    theta: np.ndarray
    std: np.ndarray
    mask: np.ndarray
    names: tuple[str, ...]

    @property
    def now(self) -> np.ndarray:
        """``[U]`` the time of each unit's last used row (its age at prediction)."""
        return np.max(np.where(self.mask, self.time, -np.inf), axis=1)

    @property
    def start(self) -> np.ndarray:
        """``[U]`` the time of each unit's first used row."""
        return np.min(np.where(self.mask, self.time, np.inf), axis=1)

    def select(self, names: Sequence[str]) -> Trajectories:
        """The trajectories of the parameters ``names`` only (in that order)."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise ValueError(
                f"parameter(s) {missing} not in the calibrated trajectories "
                f"{list(self.names)}"
            )
        idx = [self.names.index(n) for n in names]
        return dataclasses.replace(
            self, theta=self.theta[..., idx], std=self.std[..., idx], names=tuple(names)
        )

    def units(self, which: np.ndarray) -> Trajectories:
        """The units picked by ``which``: a ``[U]`` bool mask, or indices (repeats
        allowed: a unit may be seen twice, cut at two ages)."""
        which = np.asarray(which)
        index = np.flatnonzero(which) if which.dtype == bool else which
        return dataclasses.replace(
            self,
            unit=self.unit[index],
            time=self.time[index],
            theta=self.theta[index],
            std=self.std[index],
            mask=self.mask[index],
        )

    def truncated(self, keep_rows: np.ndarray) -> Trajectories:
        """Each unit's first ``keep_rows [U]`` used rows (a unit seen earlier on)."""
        rank = np.cumsum(self.mask, axis=1)
        return dataclasses.replace(
            self, mask=self.mask & (rank <= np.asarray(keep_rows)[:, None])
        )


def from_arrays(
    unit,
    time,
    theta,
    names: Sequence[str],
    std=None,
    valid=None,
    *,
    label="rows",
    min_rows: int = MIN_ROWS,
) -> Trajectories:
    """:class:`Trajectories` from per-row arrays ``unit [N]``, ``time [N]``,
    ``theta [N, P]`` (optional ``std [N, P]``, ``valid [N]``).

    Rows are grouped by unit in first-appearance order and sorted by time within a
    unit. Raises ``ValueError`` naming the unit for a unit with fewer than
    ``min_rows`` usable rows (a run-to-failure unit's trend needs :data:`MIN_ROWS`; a
    unit to predict needs one: with few rows its posterior is mostly the fleet's
    prior) or a time that repeats, and naming the rows for a non-finite time.
    """
    unit = np.asarray(unit)
    time = np.asarray(time, np.float64)
    theta = np.asarray(theta, np.float64)
    names = tuple(names)
    if theta.ndim != 2 or theta.shape != (len(unit), len(names)):
        raise ValueError(
            f"{label}: theta must be [N, {len(names)}] (columns {list(names)}), got "
            f"shape {theta.shape} for {len(unit)} rows"
        )
    std = np.full_like(theta, np.nan) if std is None else np.asarray(std, np.float64)
    ok = np.ones(len(unit), bool) if valid is None else np.asarray(valid, bool)
    bad_time = np.flatnonzero(~np.isfinite(time))
    if bad_time.size:
        raise ValueError(
            f"{label}: time is not finite in rows {bad_time[:5].tolist()} (0-based); "
            "expected a number (cycle) per row"
        )
    ok &= np.all(np.isfinite(theta), axis=1)
    ids, first, inverse = np.unique(unit, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))  # a unit's place in first-appearance order
    ids = ids[np.argsort(first)]
    key = rank[inverse.ravel()]
    used = np.flatnonzero(ok)
    order = used[np.lexsort((time[used], key[used]))]  # by unit, then by time
    counts = np.bincount(key[used], minlength=ids.size)
    short = np.flatnonzero(counts < min_rows)
    if short.size:
        u = short[0]
        raise ValueError(
            f"{label}: unit {ids[u]} has {counts[u]} usable row(s); expected at least "
            f"{min_rows} with a finite estimate"
            + (f" ({short.size} units short)" if short.size > 1 else "")
        )
    repeats = np.flatnonzero((np.diff(key[order]) == 0) & (np.diff(time[order]) == 0))
    if repeats.size:
        raise ValueError(
            f"{label}: unit {ids[key[order[repeats[0]]]]} repeats a time; expected "
            "one row per time"
        )
    length = int(counts.max())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    # each unit's rows, its last one repeated as padding
    pad = order[starts[:, None] + np.minimum(np.arange(length), counts[:, None] - 1)]
    mask = np.arange(length)[None, :] < counts[:, None]
    return Trajectories(
        unit=ids, time=time[pad], theta=theta[pad], std=std[pad], mask=mask, names=names
    )


def from_result(
    result, names: Sequence[str] | None = None, *, label="rows", min_rows=MIN_ROWS
) -> Trajectories:
    """The trajectories of a :class:`~jaxcal.calibrators.front.result.CalibrationResult`
    (its ``theta``, ``theta_std`` and ``valid``), of ``names`` (default: all)."""
    traj = from_arrays(
        result.unit, result.time, result.theta, result.theta_names,
        std=result.theta_std, valid=result.valid, label=label, min_rows=min_rows,
    )  # fmt: skip
    return traj if names is None else traj.select(names)
