"""Wild readings left out of a diagnosis: one bad reading spoils nothing.

A reading is wild when it departs from the median of its two neighbours on each
side, in its unit, by more than ``outlier_z`` robust stds of such departures
(:mod:`jaxcal.calibrators.front.outliers`, the front door's statistics). Judged against
its neighbours, a fault that persists (a step, a drift, a bias) is never an outlier; an
isolated reading off by orders of magnitude always is. ``cfg`` is the diagnosis's
:class:`~jaxcal.diagnosis.pipeline.LoopConfig`.

**A transient is not an outlier.** A model with memory answers a change of its
conditions (a set-point step) over a few rows, sharply. Where the fitted parameters
are off (the first fit is weighted by a provisional noise), the residual has a sharp
peak there too, whose top row stands out from its neighbours' median though the true
parameters explain it. Five things tell the two apart:

* A reading is also judged at the parameters **re-calibrated on its neighbours**:
  the residual linearised about the fit, ``r - J delta``, with ``J`` each row's
  sensitivity to the declared parameters and initial states (the fit's own
  signatures, a parameter's spline functions summed) and ``delta`` the move that
  best explains the rows within :data:`LOCAL_ROWS` on each side, the row itself left
  out: the deleted (leave-one-out) residual of regression diagnostics (Cook &
  Weisberg 1982, "Residuals and Influence in Regression", sec. 2.2), of a local
  regression. Each output weighs by its own spread (the robust std of its
  departures), and a ridge of :data:`LOCAL_RIDGE` of the mean information keeps
  ``delta`` at 0 where the neighbours say nothing about it (settled rows, ``J``
  flat). A reading that the model follows there is the temporary change of
  time-series outlier analysis, not its additive outlier (Chen & Liu 1993, "Joint
  estimation of model parameters and outlier effects in time series", JASA 88). A
  lone spike is followed by no ``delta``: its own row never enters it.
* A reading may instead agree with the median of the :data:`SIDE_ROWS` rows before
  it or of those after it: the edge of a step (a sensor's, or a set point's) agrees
  with its own side, where the median of both sides sits halfway up the step. A
  spike agrees with neither side.
  A reading is wild only when it departs beyond ``outlier_z`` (each comparison in
  robust stds of its own departures) in all four: from both sides, from the rows
  before, from those after, and at the re-calibrated parameters.
* A unit is judged against the wider of its own spread and the fleet's (units of at
  least :data:`UNIT_ROWS` rows): a fault whose effect follows the conditions
  roughens every row of the units that carry it, and the front door's rule holds
  that a misfit which widens all the residuals is no outlier; a few wild readings do
  not move a median.
* A reading flagged in one round is nobody's neighbour in the next (two spikes a
  row apart, or one next to a unit's first row, made their neighbours look wild).
* The refits of the iterated rejection weigh each output by its spread when the
  noise is still the reference level (:func:`drop_outliers`).

``experiments/transients.py`` measures it (``results/loop/transients.md``).
"""

from __future__ import annotations

import numpy as np

from jaxcal.calibrators.front.outliers import (
    describe_outliers,
    outlier_rows,
    robust_scale,
)
from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.fitting.joint import FitResult, fit_model, raw_columns_of

OUTLIER_ROUNDS = 4  # refits of the iterated rejection of wild readings
NEIGHBOURS = 2  # rows on each side whose median a reading is compared with
# rows on one side whose median a reading may agree with instead (the edge of a
# step): three, so that a second wild reading among them does not decide it
SIDE_ROWS = 3
# rows on each side that re-calibrate the parameters for a reading: a transient of
# the reactor (residence time 4 samples) is over in about this many
LOCAL_ROWS = 4
LOCAL_RIDGE = 1e-2  # ridge of the local fit, a share of the mean information
UNIT_ROWS = 30  # a unit judged against its own spread has at least these rows
_CHUNK = 4096  # rows per block of the local fits (bounds the memory)


def _residual(data: LoopData, fit: FitResult) -> np.ndarray:
    """``[N, S]`` each reading's residual in noise stds (NaN where not used)."""
    ev = fit.evaluation
    r = np.where(data.observed & ev.valid[:, None], data.x - ev.yhat, np.nan)
    return r / data.noise_std


def _sensitivity(data: LoopData, fit: FitResult, resid: np.ndarray) -> np.ndarray:
    """``[N, S, P]`` each reading's change, in noise stds, per natural step of each
    declared parameter held constant in time (its spline functions sum to one) and,
    for a model with memory, of each initial state (a unit's first rows answer it);
    NaN where the residual is."""
    ev, lay = fit.evaluation, fit.layout
    blocks = [b for b in lay.blocks if b.role in ("declared", "state")]
    cols = None if ev.sig is None or not blocks else raw_columns_of(ev)
    if cols is None:  # local columns come first: a block's slice indexes them
        return np.zeros(resid.shape + (0,))
    sens = np.stack([cols[:, :, b.columns].sum(axis=2) for b in blocks], axis=2)
    sens = sens / data.noise_std[:, None]
    return np.where(np.isfinite(resid)[:, :, None], sens, np.nan)


def _windows(data: LoopData, offsets, neighbour: np.ndarray):
    """``(rows [N, K], near [N, K])``: the rows at ``offsets [K]`` from each row
    (clipped into the data), and whether each is in the row's own unit and may serve
    as a neighbour (``neighbour [N]`` bool: a reading already flagged does not)."""
    rows = np.arange(data.num_rows)[:, None] + np.asarray(offsets)[None, :]
    unit = data.unit
    inside = (rows >= data.starts[unit][:, None]) & (
        rows < data.starts[unit + 1][:, None]
    )
    rows = np.clip(rows, 0, data.num_rows - 1)
    return rows, inside & neighbour[rows]


def _around(half: int) -> np.ndarray:
    """The offsets of the ``half`` rows before a row and the ``half`` after it."""
    return np.r_[np.arange(-half, 0), np.arange(1, half + 1)]


def _nan_median(values: np.ndarray, axis: int) -> np.ndarray:
    """The median along ``axis`` of the finite values (NaN where there is none):
    sorted, NaN last, the middle of the ``k`` finite ones (``np.nanmedian`` does the
    same row by row, far slower on a fleet's windows)."""
    ordered = np.sort(values, axis=axis)
    count = np.sum(~np.isnan(values), axis=axis, keepdims=True)
    low = np.take_along_axis(ordered, np.maximum(count - 1, 0) // 2, axis=axis)
    high = np.take_along_axis(ordered, count // 2 - (count == 0), axis=axis)
    middle = np.squeeze(0.5 * (low + high), axis=axis)
    return np.where(np.squeeze(count, axis=axis) > 0, middle, np.nan)


def _neighbour_departures(resid, data: LoopData, neighbour, offsets) -> np.ndarray:
    """``[N, S]`` each reading minus the median of its neighbours at ``offsets`` in
    its unit (NaN where missing)."""
    rows, near = _windows(data, offsets, neighbour)
    return resid - _nan_median(np.where(near[:, :, None], resid[rows], np.nan), axis=1)


def _local_moves(resid, sens, data: LoopData, neighbour) -> np.ndarray:
    """``[N, P]`` the declared parameters' move (natural steps) that best explains
    each row's neighbours within :data:`LOCAL_ROWS` (never the row itself), each
    output about its own local mean (a level the neighbours' median takes anyway), by
    ridge least squares (module docstring)."""
    num_p = sens.shape[2]
    if num_p == 0:  # nothing to re-calibrate: the plain departures
        return np.zeros((data.num_rows, 0))
    rows, near = _windows(data, _around(LOCAL_ROWS), neighbour)
    gram = np.zeros((data.num_rows, num_p, num_p))
    rhs = np.zeros((data.num_rows, num_p))
    for a in range(0, data.num_rows, _CHUNK):
        sl = slice(a, a + _CHUNK)
        r, j = resid[rows[sl]], sens[rows[sl]]  # [n, W, S], [n, W, S, P]
        ok = near[sl][:, :, None] & np.isfinite(r) & np.all(np.isfinite(j), axis=3)
        count = np.maximum(ok.sum(axis=1, keepdims=True), 1)
        r = np.where(ok, r, 0.0)
        j = np.where(ok[..., None], j, 0.0)
        r = np.where(ok, r - r.sum(axis=1, keepdims=True) / count, 0.0)
        j_mean = j.sum(axis=1, keepdims=True) / count[..., None]
        j = np.where(ok[..., None], j - j_mean, 0.0)
        gram[sl] = np.einsum("nwsp,nwsq->npq", j, j)
        rhs[sl] = np.einsum("nwsp,nws->np", j, r)
    info = np.mean(np.diagonal(gram, axis1=1, axis2=2), axis=0)  # [P]
    ridge = LOCAL_RIDGE * np.where(info > 0, info, 1.0)
    return np.linalg.solve(gram + np.diag(ridge), rhs[..., None])[..., 0]


def _local_departures(resid, sens, data: LoopData, neighbour) -> np.ndarray:
    """``[N, S]`` each reading minus the median of its :data:`NEIGHBOURS` on each
    side, both at the parameters re-calibrated for it (:func:`_local_moves`; the
    linearised residual ``r - J delta``)."""
    move = _local_moves(resid, sens, data, neighbour)
    rows, near = _windows(data, _around(NEIGHBOURS), neighbour)
    out = np.empty_like(resid)
    for a in range(0, data.num_rows, _CHUNK):
        sl = slice(a, a + _CHUNK)
        step = move[sl][:, None, None, :]
        others = resid[rows[sl]] - np.sum(sens[rows[sl]] * step, axis=3)  # [n, W, S]
        others = np.where(near[sl][:, :, None], others, np.nan)
        own = resid[sl] - np.sum(sens[sl] * step[:, 0], axis=2)
        out[sl] = own - _nan_median(others, axis=1)
    return out


def _spread(departure, data: LoopData, flagged) -> np.ndarray:
    """``[N, S]`` the robust std of the departures of each row's unit, or of the
    fleet's where that is wider or the unit has fewer than :data:`UNIT_ROWS` rows."""
    fleet = robust_scale(departure, ~flagged)
    out = np.tile(fleet, (data.num_rows, 1))
    for u in range(data.num_units):
        sl = slice(data.starts[u], data.starts[u + 1])
        if sl.stop - sl.start >= UNIT_ROWS:
            out[sl] = np.fmax(fleet, robust_scale(departure[sl], ~flagged[sl]))
    return out


def _standardised(data: LoopData, fit: FitResult, flagged: np.ndarray):
    """``(z [N, S], level [S])``: each reading's departure in robust stds of such
    departures, the smallest of those from its neighbours on both sides, from those
    before it, from those after it, and from its neighbours at its locally
    re-calibrated parameters (module docstring), with the sign of the first (NaN or
    infinite, never judged, where the first is); and the robust std of the
    departures from the neighbours in noise stds (the outputs' spread)."""
    resid, neighbour = _residual(data, fit), ~flagged
    both = _neighbour_departures(resid, data, neighbour, _around(NEIGHBOURS))
    level = robust_scale(both, ~flagged)
    # the local fit weighs each output by its own spread, not by the provisional
    # noise the fit was weighted by (1 % of the mean |x|, possibly far from the
    # true noise); an output without spread weighs nothing
    weight = np.where(np.isfinite(level) & (level > 0), 1.0 / level, 0.0)
    sens = _sensitivity(data, fit, resid) * weight[:, None]
    departures = (
        both,
        _neighbour_departures(resid, data, neighbour, -np.arange(SIDE_ROWS, 0, -1)),
        _neighbour_departures(resid, data, neighbour, np.arange(1, SIDE_ROWS + 1)),
        _local_departures(resid * weight, sens, data, neighbour),
    )
    with np.errstate(all="ignore"):
        z = [d / _spread(d, data, flagged) for d in departures]
        smallest = np.fmin.reduce([np.abs(zi) for zi in z])  # NaN: no such neighbour
        return np.where(np.isfinite(z[0]), np.sign(z[0]) * smallest, z[0]), level


def drop_outliers(model, data: LoopData, spec0, null: FitResult, cfg):
    """``(data, fit)`` without the rows holding a wild reading (module docstring).

    A wild reading drags the fit it is in, so the rows are judged again, every one,
    by the fit without the flagged ones, until the flags stop changing (iterated
    rejection; at most :data:`OUTLIER_ROUNDS` refits). Those refits weigh each
    output by its own spread when the noise is the provisional reference level
    (:mod:`jaxcal.diagnosis.data.prepare`), not a given or estimated one: weighted
    by the reference, a fit can trade one output for another, and that fit's misfit
    at each change of the conditions, the rows it was flagged on, goes with it."""
    if cfg.outlier_z is None:
        return data, null
    flagged, fit, found, judge = np.zeros(data.num_rows, bool), null, None, data
    for _ in range(OUTLIER_ROUNDS):
        z, level = _standardised(data, fit, flagged)
        found = outlier_rows(z, threshold=cfg.outlier_z)
        if np.array_equal(found.mask, flagged):
            break
        if not flagged.any() and data.noise_source == "reference":
            judge = _weighted_by_spread(data, level)
        flagged = found.mask
        if not flagged.any():
            return data, null
        fit = fit_model(model, judge.mask_rows(~flagged, ""), spec0,
                        max_iters=cfg.max_iters)  # fmt: skip
    if not found.mask.any():
        return data, null
    note = (
        describe_outliers(found, data.unit_ids[data.unit], data.sensor_names)
        + f" left out (a reading beyond {cfg.outlier_z:g} robust stds of its "
        "neighbours, also at the parameters re-calibrated on them)"
    )
    keep = ~found.mask
    if model.is_stateful:
        data = data.mask_rows(keep, note)
    else:
        data = data.take_rows(keep, note)
    return data, fit_model(model, data, spec0, max_iters=cfg.max_iters)


def _weighted_by_spread(data: LoopData, level: np.ndarray) -> LoopData:
    """``data`` whose white noise is each output's spread (``level``, in noise stds,
    from :func:`_standardised`; the reference level where it has none): the weights
    of the screening's refits (:func:`drop_outliers`)."""
    ok = np.isfinite(level) & (level > 0)
    std = data.noise_std * np.where(ok, level, 1.0)
    return data.with_noise(data.noise.with_sigma(std, data.noise_source))
