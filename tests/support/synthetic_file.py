"""A small synthetic N-CMAPSS file, for smoke runs and tests of the training job.

The real generator (``python -m jaxcal.generate dataset=tiny``) needs the engine model
(tens of seconds of compilation); this file needs nothing but numpy. Each unit flies
smooth random operating conditions w (alt, Mach, TRA, T2 in the N-CMAPSS ranges) while
``HPT_eff_mod`` degrades linearly at a unit-specific rate; the 28 N-CMAPSS sensors are a
fixed smooth function of (w, theta):

    x_j = m_j (1 + 0.05 tanh(a_j . w_n) + 0.5 b_j theta_HPT_eff),

with w_n the standardised conditions and (m, a, b) drawn once from ``seed``. The layout,
names and splits are those of the real files (``W_dev``, ``X_s_dev``, ..., ``*_var``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jaxcal.models.turbofan.data.ncmapss_io import write_ncmapss
from jaxcal.models.turbofan.data.record import Record
from jaxcal.models.turbofan.physics.constants import (
    HEALTH_NAMES,
    MEASURED_SENSOR_NAMES,
    VIRTUAL_SENSOR_NAMES,
)

_SENSORS = MEASURED_SENSOR_NAMES + VIRTUAL_SENSOR_NAMES
_W_CENTRE = np.array([22_000.0, 0.5, 55.0, 470.0])
_W_SCALE = np.array([8_000.0, 0.15, 20.0, 25.0])


def _unit_record(unit: int, num_rows: int, model: dict, rng) -> Record:
    t = np.linspace(0.0, 1.0, num_rows)[:, None]
    freq = rng.uniform(2.0, 6.0, (1, 4))
    phase = rng.uniform(0.0, 2 * np.pi, (1, 4))
    w_n = np.sin(2 * np.pi * freq * t + phase)
    theta = np.zeros((num_rows, len(HEALTH_NAMES)))
    hpt = HEALTH_NAMES.index("HPT_eff_mod")
    theta[:, hpt] = -0.002 - rng.uniform(0.008, 0.015) * t[:, 0]
    x = model["m"] * (
        1.0
        + 0.05 * np.tanh(w_n @ model["a"])
        + 0.5 * theta[:, hpt : hpt + 1] * model["b"]
    )
    cycle = 1 + (np.arange(num_rows) * 3) // num_rows
    return Record(
        w=_W_CENTRE + _W_SCALE * w_n,
        x=x,
        x_names=_SENSORS,
        theta=theta,
        unit=np.full(num_rows, unit),
        cycle=cycle,
        flight_class=np.full(num_rows, 1.0 + unit % 3),
        hs=(cycle < 3).astype(float),
        rul=cycle.max() - cycle,
        source="synthetic",
    )


def _concat(records: list[Record]) -> Record:
    def cat(name):
        return np.concatenate([getattr(r, name) for r in records])

    return Record(
        w=cat("w"),
        x=cat("x"),
        x_names=records[0].x_names,
        theta=cat("theta"),
        unit=cat("unit"),
        cycle=cat("cycle"),
        flight_class=cat("flight_class"),
        hs=cat("hs"),
        rul=cat("rul"),
        source="synthetic",
    )


def write_synthetic_ncmapss(
    path: str | os.PathLike,
    *,
    dev_units: tuple[int, ...] = (1, 2, 3),
    test_units: tuple[int, ...] = (4, 5),
    num_rows: int = 120,
    seed: int = 0,
    attrs: dict | None = None,
) -> Path:
    """Write a synthetic N-CMAPSS file (atomically) and return its path.

    Args:
        path: destination ``.h5``; its folder must exist.
        dev_units, test_units: unit ids of the two splits.
        num_rows: rows of the first unit; unit k has ``num_rows + 7 k`` rows, so
            units differ in length (padding is exercised).
        seed: draws the sensor model and the flights.
        attrs: extra root attributes (e.g. ``{"observed_sensors": [...]}``).

    Returns:
        ``Path(path)``.
    """
    if num_rows < 8 or not dev_units or not test_units:
        raise ValueError("need num_rows >= 8 and at least one dev and one test unit")
    rng = np.random.default_rng(seed)
    num = len(_SENSORS)
    model = {
        "m": rng.uniform(5.0, 2_000.0, (1, num)),
        "a": rng.normal(size=(4, num)),
        "b": rng.uniform(0.5, 2.0, (1, num)),
    }
    splits = []
    for units in (dev_units, test_units):
        records = [
            _unit_record(u, num_rows + 7 * k, model, rng) for k, u in enumerate(units)
        ]
        splits.append(_concat(records))
    write_ncmapss(path, splits[0], splits[1], attrs=attrs)
    return Path(path)
