"""The host-side container that every data loader of jaxcal returns.

A :class:`Record` is a flat table of ``N`` samples in N-CMAPSS vocabulary and units: the
operating conditions ``w`` (``W``), the sensors ``x`` (``X_s`` / ``X_v`` / C-MAPSS
extras, named by :data:`~jaxcal.models.turbofan.physics.constants.SENSOR_NAMES`), the
health modifiers ``theta`` (``T``) when the source knows them, the auxiliary columns
``A`` (unit, cycle, flight class, health state) and the RUL ``Y``. The HDF5 reader
(:mod:`jaxcal.models.turbofan.data.ncmapss_io`) and the C-MAPSS text reader
(:mod:`jaxcal.models.turbofan.data.cmapss_text`) both produce it, so downstream code
does not care where the data came from. Arrays are numpy (host side);
:meth:`Record.padded` turns a Record into the one padded container,
:class:`~jaxcal.data.padded.Padded`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence

import numpy as np

from jaxcal.data.padded import Padded
from jaxcal.models.turbofan.physics.constants import (
    CONDITION_NAMES,
    HEALTH_NAMES,
    SENSOR_NAMES,
)


def _as_int64(name: str, value) -> np.ndarray:
    """``value`` as a 1-D int64 array; float input must hold integers exactly."""
    arr = np.asarray(value)
    if arr.ndim != 1:
        raise ValueError(f"Record.{name} must be 1-D [N], got shape {arr.shape}")
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise ValueError(
                f"Record.{name} must hold integers, got non-integer floats"
            )
    elif arr.dtype.kind not in "iub":
        raise ValueError(f"Record.{name} must be an integer array, got {arr.dtype}")
    return arr.astype(np.int64, copy=False)


def _as_float_matrix(name: str, value, num_rows: int, num_cols: int) -> np.ndarray:
    """``value`` as a float64 ``[num_rows, num_cols]`` array, or a clear error."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (num_rows, num_cols):
        raise ValueError(
            f"Record.{name} must have shape [N={num_rows}, {num_cols}], got {arr.shape}"
        )
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class Record:
    """``N`` samples of one data split, in N-CMAPSS names and units.

    Attributes:
        w: ``[N, 4]`` operating conditions in :data:`CONDITION_NAMES` order
            (alt ft, Mach, TRA %, T2 degR).
        x: ``[N, S]`` sensor values, column ``j`` named ``x_names[j]``.
        x_names: ``S`` sensor names, each one of :data:`SENSOR_NAMES`, no repeats.
        theta: ``[N, 10]`` health modifiers in :data:`HEALTH_NAMES` order, or ``None``
            when the source has no ground truth (real C-MAPSS text files).
        unit: ``[N]`` int64 engine unit id.
        cycle: ``[N]`` int64 flight (cycle) number.
        flight_class: ``[N]`` float64 N-CMAPSS flight class Fc (1, 2, 3); NaN if
            unknown.
        hs: ``[N]`` float64 health state (1 normal, 0 abnormal degradation); NaN if
            unknown.
        rul: ``[N]`` int64 remaining useful life in cycles; -1 when unknown.
        extras: source columns with no N-CMAPSS name, each ``[N]`` (e.g. the C-MAPSS
            ``htBleed``). Names must not repeat a name of ``x_names``.
        sample_rate_hz: rows per second within a flight (1.0 for N-CMAPSS). NaN means
            the source has no within-flight time base (C-MAPSS: one row per flight).
        source: free-text provenance (file path and split).
        dropped: column -> rows the reader dropped for a NaN / Inf in that column
            (``nonfinite="drop"``); a row bad in two columns counts in both.
        dropped_rows: rows dropped in total (each row once).
    """

    w: np.ndarray
    x: np.ndarray
    x_names: tuple[str, ...]
    theta: np.ndarray | None
    unit: np.ndarray
    cycle: np.ndarray
    flight_class: np.ndarray
    hs: np.ndarray
    rul: np.ndarray
    extras: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    sample_rate_hz: float = 1.0
    source: str = ""
    dropped: dict[str, int] = dataclasses.field(default_factory=dict)
    dropped_rows: int = 0

    def __post_init__(self):
        # Coerce to the documented dtypes once, here, so every consumer can rely on
        # them; object.__setattr__ is how a frozen dataclass normalises its own fields.
        set_ = object.__setattr__
        unit = _as_int64("unit", self.unit)
        n = unit.shape[0]
        set_(self, "unit", unit)
        set_(self, "cycle", _as_int64("cycle", self.cycle))
        set_(self, "rul", _as_int64("rul", self.rul))
        for name in ("cycle", "rul"):
            if getattr(self, name).shape != (n,):
                raise ValueError(
                    f"Record.{name} must have shape [N={n}] like Record.unit, "
                    f"got {getattr(self, name).shape}"
                )
        for name in ("flight_class", "hs"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != (n,):
                raise ValueError(
                    f"Record.{name} must have shape [N={n}], got {arr.shape}"
                )
            set_(self, name, arr)

        names = tuple(str(s) for s in self.x_names)
        unknown = [s for s in names if s not in SENSOR_NAMES]
        if unknown:
            raise ValueError(
                f"Record.x_names has unknown sensor name(s) {unknown}; valid names are "
                f"{list(SENSOR_NAMES)} (put other columns in Record.extras)"
            )
        if len(set(names)) != len(names):
            raise ValueError(f"Record.x_names has repeated names: {list(names)}")
        set_(self, "x_names", names)
        set_(self, "w", _as_float_matrix("w", self.w, n, len(CONDITION_NAMES)))
        set_(self, "x", _as_float_matrix("x", self.x, n, len(names)))
        if self.theta is not None:
            set_(
                self,
                "theta",
                _as_float_matrix("theta", self.theta, n, len(HEALTH_NAMES)),
            )

        extras = {}
        for key, value in dict(self.extras).items():
            arr = np.asarray(value)
            if arr.shape[:1] != (n,):
                raise ValueError(
                    f"Record.extras[{key!r}] must have leading dimension N={n}, "
                    f"got shape {arr.shape}"
                )
            if key in names:
                raise ValueError(f"Record.extras[{key!r}] repeats a name of x_names")
            extras[str(key)] = arr
        set_(self, "extras", extras)

        rate = float(self.sample_rate_hz)
        if not (np.isnan(rate) or (np.isfinite(rate) and rate > 0)):
            raise ValueError(
                f"Record.sample_rate_hz must be > 0 (or NaN for one row per flight), "
                f"got {self.sample_rate_hz}"
            )
        set_(self, "sample_rate_hz", rate)
        dropped = {str(k): int(v) for k, v in dict(self.dropped).items()}
        if any(v < 0 for v in dropped.values()) or int(self.dropped_rows) < 0:
            raise ValueError(
                "Record.dropped counts and Record.dropped_rows must be >= 0, got "
                f"{dropped} and {self.dropped_rows}"
            )
        set_(self, "dropped", dropped)
        set_(self, "dropped_rows", int(self.dropped_rows))

    @property
    def num_rows(self) -> int:
        """Number of samples ``N``."""
        return int(self.unit.shape[0])

    def __len__(self) -> int:
        return self.num_rows

    @property
    def units(self) -> np.ndarray:
        """Sorted unique unit ids, ``[U]`` int64."""
        return np.unique(self.unit)

    def take(self, index) -> Record:
        """The rows picked by ``index`` (an integer index array, slice or bool mask).

        Args:
            index: anything numpy accepts as a row index of a 1-D array of length ``N``.

        Returns:
            A new Record with the selected rows, in the order of ``index``.
        """
        return dataclasses.replace(
            self,
            w=self.w[index],
            x=self.x[index],
            theta=None if self.theta is None else self.theta[index],
            unit=self.unit[index],
            cycle=self.cycle[index],
            flight_class=self.flight_class[index],
            hs=self.hs[index],
            rul=self.rul[index],
            extras={k: v[index] for k, v in self.extras.items()},
        )

    def select_units(self, units: Iterable[int]) -> Record:
        """The rows of the given units (row order preserved).

        Args:
            units: unit ids; each must occur in :attr:`unit`.

        Returns:
            A Record restricted to those units.
        """
        wanted = np.asarray(list(units), dtype=np.int64)
        missing = sorted(set(wanted.tolist()) - set(self.units.tolist()))
        if missing:
            raise ValueError(
                f"unit(s) {missing} not in the record; available units are "
                f"{self.units.tolist()}"
            )
        return self.take(np.isin(self.unit, wanted))

    def padded(self, dtype=np.float64, max_len: int | None = None) -> Padded:
        """The units as one :class:`~jaxcal.data.padded.Padded` (host numpy).

        Units come in ascending id order, the rows of a unit in record order (file
        order is time order); padding repeats a unit's last row. ``theta`` is all
        ten health modifiers, zeros when the source has none; ``rows`` is ``None``.

        Args:
            dtype: float dtype of ``w``, ``x`` and ``theta``.
            max_len: common length ``T``; ``None``: the longest unit. A longer unit
                is an error, never truncated.
        """
        if self.num_rows == 0:
            raise ValueError("padding needs a record with at least one row")
        unit_ids, inverse, counts = np.unique(
            self.unit, return_inverse=True, return_counts=True
        )
        order = np.argsort(inverse, kind="stable")  # group by unit, keep time order
        longest = int(counts.max())
        max_len = longest if max_len is None else int(max_len)
        if max_len < longest:
            raise ValueError(
                f"{self.source}: max_len={max_len} is shorter than a unit of {longest} "
                f"rows among units {unit_ids.tolist()}; raise max_len"
            )
        # Index of the source row of every (unit, step): the padding repeats the last.
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        steps = np.minimum(np.arange(max_len)[None, :], counts[:, None] - 1)
        source = order[starts[:, None] + steps]  # [U, T]
        theta = (
            self.theta[source]
            if self.theta is not None
            else np.zeros((len(unit_ids), max_len, len(HEALTH_NAMES)))
        )
        return Padded(
            w=self.w[source].astype(dtype),
            x=self.x[source].astype(dtype),
            theta=theta.astype(dtype),
            lengths=counts.astype(np.int32),
            unit_ids=unit_ids.astype(np.int64),
            cycle=self.cycle[source],
        )

    def columns(self, names: Sequence[str]) -> np.ndarray:
        """Columns of ``x`` (or of ``extras``) by name.

        Args:
            names: sensor names of :attr:`x_names`, or keys of :attr:`extras`.

        Returns:
            ``[N, len(names)]`` float64 array, columns in the order of ``names``.
        """
        if isinstance(names, str):
            raise ValueError(
                f"columns() takes a sequence of names, got the string {names!r}"
            )
        available = list(self.x_names) + list(self.extras)
        unknown = [n for n in names if n not in available]
        if unknown:
            raise ValueError(
                f"column(s) {unknown} not in the record; available columns are "
                f"{available}"
            )
        out = np.empty((self.num_rows, len(names)), dtype=np.float64)
        for j, n in enumerate(names):
            if n in self.x_names:
                out[:, j] = self.x[:, self.x_names.index(n)]
            else:
                out[:, j] = self.extras[n]
        return out
