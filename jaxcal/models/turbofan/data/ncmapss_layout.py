"""N-CMAPSS HDF5 layout: group names, column names, dtypes and record checks.

Shared by :mod:`jaxcal.models.turbofan.data.ncmapss_writer` and
:mod:`jaxcal.models.turbofan.data.ncmapss_reader` (see
:mod:`jaxcal.models.turbofan.data.ncmapss_io` for the layout itself).
"""

from __future__ import annotations

import json

import numpy as np

from jaxcal.models.turbofan.data.record import Record
from jaxcal.models.turbofan.physics.constants import (
    AUX_NAMES,
    CONDITION_NAMES,
    HEALTH_NAMES,
    MEASURED_SENSOR_NAMES,
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
