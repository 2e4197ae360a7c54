"""Output noise levels estimated from the residual of a first calibration.

:func:`estimate_noise_std` pairs, within each unit, every row with its nearest
neighbour in standardised (w, time) space and takes ``1.4826 MAD(r_i - r_j) /
sqrt(2)``. Differencing removes what the model misses smoothly in w and time (the pair
shares the operating point), the MAD ignores the few pairs that do not, and raw first
differences would not work on data whose consecutive rows visit different operating
conditions (C-MAPSS flies a different condition every cycle). The start level before
this estimate is the model's reference (``DiagnosisHints.noise_rel``, see
:mod:`.problem`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from jaxcal.diagnosis.prepare import LoopData


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
        for j in range(data.w.shape[1])
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
