"""Wild readings left out of a diagnosis (issue 25: one bad reading spoils nothing).

A reading is wild when it departs from the median of its two neighbours on each
side, in its unit, by more than ``outlier_z`` robust stds of such departures
(:mod:`jaxcal.calibrators.outliers`, the front door's statistics). Judged against its
neighbours, a fault that persists (a step, a drift, a bias) is never an outlier; an
isolated reading off by orders of magnitude always is. ``cfg`` is the diagnosis's
:class:`~jaxcal.diagnosis.pipeline.LoopConfig`.
"""

from __future__ import annotations

import warnings

import numpy as np

from jaxcal.calibrators.outliers import describe_outliers, outlier_rows, robust_scale
from jaxcal.diagnosis.fitting import FitResult, fit_model
from jaxcal.diagnosis.prepare import LoopData

OUTLIER_ROUNDS = 4  # refits of the iterated rejection of wild readings


def _departures(data: LoopData, fit: FitResult) -> np.ndarray:
    """``[N, S]`` each reading's residual (every row, in noise stds) minus the median
    of its two neighbours on each side in its unit (NaN where missing)."""
    ev = fit.evaluation
    r = np.where(data.observed & ev.valid[:, None], data.x - ev.yhat, np.nan)
    r = r / data.noise_std
    local = np.empty_like(r)
    for u in range(data.num_units):
        sl = slice(data.starts[u], data.starts[u + 1])
        padded = np.pad(r[sl], ((2, 2), (0, 0)), mode="edge")
        window = np.lib.stride_tricks.sliding_window_view(padded, 5, axis=0)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an all-missing window
            local[sl] = np.nanmedian(np.delete(window, 2, axis=2), axis=2)
    return r - local


def drop_outliers(model, data: LoopData, spec0, null: FitResult, cfg):
    """``(data, fit)`` without the rows holding a wild reading: one that departs from
    the median of its two neighbours on each side by more than ``outlier_z`` robust
    stds of such departures (:mod:`jaxcal.calibrators.outliers`). Judged against its
    neighbours, a fault that persists (a step, a drift, a bias) is never an outlier;
    an isolated reading off by orders of magnitude always is. A wild reading drags
    the fit it is in, so the rows are judged again, every one, by the fit without the
    flagged ones, until the flags stop changing (iterated rejection; at most
    :data:`OUTLIER_ROUNDS` refits)."""
    if cfg.outlier_z is None:
        return data, null
    flagged, fit, found = np.zeros(data.num_rows, bool), null, None
    for _ in range(OUTLIER_ROUNDS):
        departure = _departures(data, fit)
        scale = robust_scale(departure, ~flagged)
        found = outlier_rows(departure, scale, threshold=cfg.outlier_z)
        if np.array_equal(found.mask, flagged):
            break
        flagged = found.mask
        if not flagged.any():
            return data, null
        fit = fit_model(model, data.mask_rows(~flagged, ""), spec0,
                        max_iters=cfg.max_iters)  # fmt: skip
    if not found.mask.any():
        return data, null
    note = (
        describe_outliers(found, data.unit_ids[data.unit], data.sensor_names)
        + f" left out (a reading beyond {cfg.outlier_z:g} robust stds of its "
        "neighbours)"
    )
    keep = ~found.mask
    if model.is_stateful:
        data = data.mask_rows(keep, note)
    else:
        data = data.take_rows(keep, note)
    return data, fit_model(model, data, spec0, max_iters=cfg.max_iters)
