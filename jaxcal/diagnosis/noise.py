"""Sensor noise levels: C-MAPSS reference levels and an estimate from a residual.

:func:`reference_noise_rel` gives each sensor's relative noise std from the early life
of C-MAPSS FD002 (:mod:`jaxcal.physics.reference`); the synthetic records use it, and
the diagnosis starts from it when the noise is unknown.

:func:`estimate_noise_std` estimates the noise from the residual of a first calibration:
within each unit it pairs every row with its nearest neighbour in standardised
(w, cycle) space and takes ``1.4826 MAD(r_i - r_j) / sqrt(2)``. Differencing removes
what the model misses smoothly in w and cycle (the pair shares the operating point), the
MAD ignores the few pairs that do not, and raw first differences would not work on
C-MAPSS, whose consecutive cycles fly different operating conditions.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from jaxcal.physics.reference import FD002_EARLY_MEANS, FD002_EARLY_STD

if TYPE_CHECKING:
    from jaxcal.diagnosis.problem import LoopData

# Sensors without a measured C-MAPSS noise level borrow the relative level of a sensor
# of the same kind (temperature, pressure, speed, flow).
NOISE_PROXY = {
    "T48": "T50",
    "T40": "T50",
    "P15": "P30",
    "P2": "P30",
    "P21": "P30",
    "P24": "P30",
    "Ps30": "P30",
    "P40": "P30",
    "P50": "P30",
    "P45": "P30",
    "epr": "P30",
    "Nf": "Nc",
    "NRf": "Nc",
    "NRc": "Nc",
    "Nf_dmd": "Nc",
    "PCNfR_dmd": "Nc",
    "Wf": "W31",
    "W21": "W31",
    "W22": "W31",
    "W25": "W31",
    "W48": "W31",
    "W50": "W31",
    "phi": "W31",
    "farB": "W31",
    "SmFan": "BPR",
    "SmLPC": "BPR",
    "SmHPC": "BPR",
}


def reference_noise_rel(name: str) -> float:
    """Relative noise std (std / mean) of a sensor, from the C-MAPSS FD002 early life.

    The median over the six operating conditions of ``FD002_EARLY_STD /
    FD002_EARLY_MEANS`` (jaxcal.physics.reference); sensors C-MAPSS does not measure
    use the proxy of :data:`NOISE_PROXY`.
    """
    key = NOISE_PROXY.get(name, name)
    if key not in FD002_EARLY_STD:
        raise ValueError(f"no reference noise level for sensor {name!r}")
    ratio = np.asarray(FD002_EARLY_STD[key]) / np.abs(FD002_EARLY_MEANS[key])
    return float(np.median(ratio))


def estimate_noise_std(
    data: LoopData, resid: np.ndarray, *, block: int = 1024
) -> tuple[np.ndarray, dict[str, str]]:
    """Noise std from nearest-neighbour differences of a residual (module docstring).

    Args:
        data: the rows.
        resid: ``[N, S]`` residual ``x - xhat`` of a first calibration, sensor units.
        block: rows per distance block (bounds memory).

    Returns:
        ``(std [S], reasons)``: ``reasons`` names sensors to exclude, because the
        estimate is zero or the rounding step of the raw values dominates it.
    """
    w_std = data.w.std(0)
    feats = [
        (data.w[:, j] - data.w[:, j].mean()) / w_std[j]
        for j in range(4)
        if w_std[j] > 0
    ]
    span = np.maximum(
        np.maximum.reduceat(data.cycle, data.starts[:-1])
        - np.minimum.reduceat(data.cycle, data.starts[:-1]),
        1.0,
    )
    feats.append(data.cycle / span[data.unit])
    z = np.stack(feats, axis=1)
    diffs = []
    for u in range(data.num_units):
        a, b = data.starts[u], data.starts[u + 1]
        if b - a < 2:
            continue
        zu, ru = z[a:b], resid[a:b]
        for c in range(0, b - a, block):
            d2 = ((zu[c : c + block, None, :] - zu[None, :, :]) ** 2).sum(-1)
            d2[np.arange(d2.shape[0]), c + np.arange(d2.shape[0])] = np.inf
            diffs.append(ru[c : c + block] - ru[np.argmin(d2, axis=1)])
    if not diffs:
        raise ValueError("noise estimation needs a unit with at least two rows")
    d = np.concatenate(diffs, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    std = 1.4826 * mad / np.sqrt(2.0)
    reasons = {}
    for j, s in enumerate(data.sensor_names):
        values = np.unique(data.x[:, j])
        step = np.diff(values).min() if values.size > 1 else 0.0
        if not std[j] > 0:
            reasons[s] = "noise estimate is zero (constant or rounded readings)"
        elif step / np.sqrt(12.0) > 0.5 * std[j]:
            reasons[s] = (
                f"quantised: rounding step {step:.3g} dominates the noise "
                f"estimate {std[j]:.3g}"
            )
    return std, reasons
