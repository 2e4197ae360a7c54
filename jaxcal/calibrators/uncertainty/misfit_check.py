"""Where the model misfits the data, the reported theta std is flagged, not widened.

A filter's (and least squares') std assumes white measurement noise. A model that
misfits the data leaves errors correlated over many rows, and two things follow:
such errors carry less information than white ones, so the std is too small by the
square root of their long-run variance over their variance (the effective-sample-
size argument behind the HAC variance of Newey & West 1987, Econometrica 55); and a
parameter absorbs the part of the misfit its sensitivity can explain, a bias that
no residual shows.

The second is why the std is flagged here and not widened: on the battery example
(an ECM tracking PyBaMM SPMe cells) the innovations' colour is alike on every cell
while R0's error is a bias growing with the cell's loss of active material; no
single factor read off the residuals makes both parameters' stds honest
(``experiments/misfit_battery.py``, ``results/std_coverage/misfit_battery.md``).
Least squares is flagged all the same: a check against its own later estimates
cannot see a bias they share.

So, per unit and output, the one-step innovations of the screening's UKF pass
(``x_t - E[x_t | past]`` over its predicted std: white for a filter whose model and
noise are right, Mehra 1970, IEEE TAC 15) are read over the unit's settled used rows
in time order, and their long-run variance ratio estimated with the Bartlett kernel
and Andrews' (1991, Econometrica 59) AR(1) plug-in bandwidth. A unit is flagged
where an output's ratio exceeds :data:`COLOURED` (the std at least 2x too small from
the colour alone): ``result.misfit`` marks its rows and a note names it.

Two more readings of the same innovations (``experiments/reactor.py``). A misfit
that starts late colours a few dozen rows before the parameters absorb it, so the
whole unit's ratio stays near 1: Page's CUSUM of the innovations
(:func:`shift_statistic`) flags it past :data:`SHIFTED` stds. And a noise that is
itself coloured leaves a ratio under the flag with a std too small: where the
innovations fit an AR(p) noise (Yule-Walker, BIC order) without shift and under the
flag, the std of a method that assumes white noise
(:attr:`~jaxcal.calibrators.methods.protocol.Method.white_std`) is widened by the
square root of that AR fit's long-run variance ratio (:func:`ar_long_run_ratio`; the
Bartlett estimate, bandwidth-truncated, reads a persistent colour low). Why widen
here and not for the battery: here the colour comes from the noise, whose long-run
variance is what the estimate's variance scales with (fewer independent rows).

A filter that lags a drift faster than its random walk, or an output quantised far
coarser than its noise, colours the innovations too, and its std is no more to be
trusted: the note names all three causes.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pandas as pd

from jaxcal.calibrators.front.outliers import MAD_TO_STD
from jaxcal.calibrators.uncertainty.jitter_check import settled_rows, units_shown

# flagged where the long-run variance is this many times the variance: the std at
# least 2x too small from the colour alone (measured: <= 1.22 well specified, >= 17
# on the battery under model error)
COLOURED = 4.0
MIN_ROWS = 30  # a unit's output needs this many settled used rows to be judged
ANDREWS = 1.1447  # Andrews (1991): the Bartlett kernel's plug-in constant
RHO_MAX = 0.97  # the AR(1) coefficient of the plug-in, kept off 1 (Andrews 1991)
MAX_AR = 6  # the highest AR order fitted to a unit's innovations
# Page's CUSUM: the drift is half the shift of one std it is tuned to; flagged past
# SHIFTED stds (measured: the well-specified cases of experiments/std_coverage.py
# and the reactor with white or AR(1) noise <= 7.7; the reactor's 1.5 K sensor bias
# from row 300 of 500 11.3-18; Basseville & Nikiforov 1993, sec. 2.2)
CUSUM_DRIFT = 0.5
SHIFTED = 10.0
# a unit's std is widened by sqrt(AR long-run variance ratio) where that is above
# this (the std at least 1.22x too small from the colour)
WIDEN_FROM = 1.5


def autocorrelation(series: np.ndarray) -> np.ndarray:
    """``[T]`` the sample autocorrelation of ``series [T]`` at lags ``0..T-1`` (the
    biased estimator, by FFT: statsmodels' ``acf(fft=True)``, whose import alone
    costs seconds)."""
    centred = series - series.mean()
    n = len(centred)
    spectrum = np.fft.rfft(centred, 2 * n)
    covariance = np.fft.irfft(spectrum * np.conj(spectrum), 2 * n)[:n]
    return covariance / covariance[0] if covariance[0] > 0 else np.zeros(n)


def long_run_ratio(series: np.ndarray) -> float:
    """Bartlett-kernel long-run variance of ``series [T]`` over its variance.

    1 for white noise, ``(1 + rho) / (1 - rho)`` for an AR(1) (at a long enough
    bandwidth); the bandwidth is Andrews' AR(1) plug-in, at most a quarter of the
    series."""
    n = len(series)
    rho = autocorrelation(series)
    rho1 = float(np.clip(rho[1], -RHO_MAX, RHO_MAX))
    alpha = 4 * rho1**2 / ((1 - rho1) ** 2 * (1 + rho1) ** 2)
    bandwidth = int(np.clip(ANDREWS * (alpha * n) ** (1 / 3), 1, n // 4))
    weights = 1 - np.arange(1, bandwidth + 1) / (bandwidth + 1)
    return max(0.0, 1 + 2 * float(np.sum(weights * rho[1 : bandwidth + 1])))


def ar_long_run_ratio(series: np.ndarray) -> float:
    """Long-run variance over variance of the AR(p) fitted to ``series [T]``.

    Yule-Walker fits of every order up to :data:`MAX_AR` (Levinson's Toeplitz
    solve), the order by BIC (order 0, white: 1). For AR coefficients ``phi`` and
    innovation variance ``v`` (a share of the variance) the ratio is ``v / (1 -
    sum(phi))^2``: ``(1 + phi) / (1 - phi)`` for an AR(1). Unlike the Bartlett
    estimate (:func:`long_run_ratio`), whose bandwidth truncates a slowly decaying
    autocorrelation, it is not biased low for a persistent noise."""
    # light --help: scipy loads when a misfit is checked (the train and fleet
    # command lines import the front door before their arguments are checked)
    from scipy.linalg import solve_toeplitz

    n = len(series)
    rho = autocorrelation(series)
    if rho[0] <= 0:
        return 1.0
    best_bic, ratio = 0.0, 1.0
    for p in range(1, min(MAX_AR, n // 10) + 1):
        phi = solve_toeplitz(rho[:p], rho[1 : p + 1])
        share = 1.0 - float(phi @ rho[1 : p + 1])
        if not 0.0 < share <= 1.0 or abs(1.0 - phi.sum()) < 1e-6:
            break  # not a stationary fit: keep the last one that was
        bic = n * np.log(share) + p * np.log(n)
        if bic < best_bic:
            best_bic, ratio = bic, share / (1.0 - float(phi.sum())) ** 2
    return ratio


def shift_statistic(series: np.ndarray) -> float:
    """Page's two-sided CUSUM (drift :data:`CUSUM_DRIFT`) of ``series [T]`` about its
    median, over its robust std times the square root of its AR long-run variance
    ratio (so that a coloured but stationary noise does not count as a shift): the
    largest excursion, in those stds."""
    centred = series - np.median(series)
    scale = MAD_TO_STD * np.median(np.abs(centred))
    if not scale > 0:
        return 0.0
    scale *= np.sqrt(max(1.0, ar_long_run_ratio(centred)))
    high = low = best = 0.0
    for value in centred / scale:  # a few hundred rows a unit: a loop is cheap
        high = max(0.0, high + value - CUSUM_DRIFT)
        low = max(0.0, low - value - CUSUM_DRIFT)
        best = max(best, high, low)
    return best


class Colour(NamedTuple):
    """What :func:`colour_rows` reads off the innovations, per row of the data.

    Attributes:
        misfit: ``[N]`` True on every row of a unit flagged as misfitting.
        ratio: ``[N, S]`` the unit's Bartlett long-run variance ratio per output.
        shift: ``[N, S]`` the unit's CUSUM statistic per output.
        widen: ``[N]`` the factor the unit's std is widened by for a coloured
            noise (1 where white, or flagged: nothing to widen).
        (``nan`` in ``ratio`` and ``shift`` where not judged: fewer than
        :data:`MIN_ROWS` settled used rows.)
    """

    misfit: np.ndarray
    ratio: np.ndarray
    shift: np.ndarray
    widen: np.ndarray


def colour_rows(
    unit: np.ndarray, time: np.ndarray, z: np.ndarray, used: np.ndarray
) -> Colour:
    """The units whose innovations show a misfit, and the others' colour (module
    doc).

    Args:
        unit, time: ``[N]`` each row's unit and time (any row order).
        z: ``[N, S]`` the one-step innovations over their predicted std (``nan``
            where an output is missing).
        used: ``[N]`` bool, the rows the pass used (outliers and skipped rows not).
    """
    nothing = np.full(z.shape, np.nan)
    # the filter's first rows are its settling, not the model's fit
    order, keep = settled_rows(unit, time, used)
    if not keep.any():  # nothing to judge by
        return Colour(np.zeros(len(unit), bool), nothing, nothing, np.ones(len(unit)))
    kept_unit, kept_z = unit[order][keep], z[order][keep]
    starts = np.flatnonzero(np.r_[True, kept_unit[1:] != kept_unit[:-1]])
    stats = {}  # a unit with no kept row is not judged (nan)
    for u, rows in zip(kept_unit[starts], np.split(kept_z, starts[1:]), strict=True):
        cols = [col[np.isfinite(col)] for col in rows.T]
        judged = [len(col) >= MIN_ROWS for col in cols]
        stats[u] = [
            [f(col) if ok else np.nan for col, ok in zip(cols, judged, strict=True)]
            for f in (long_run_ratio, shift_statistic, ar_long_run_ratio)
        ]

    def per_row(k: int) -> np.ndarray:
        table = pd.DataFrame.from_dict(
            {u: v[k] for u, v in stats.items()}, orient="index",
            columns=range(z.shape[1]),
        )  # fmt: skip
        return table.reindex(unit).to_numpy(np.float64)

    ratio, shift, ar_ratio = per_row(0), per_row(1), per_row(2)
    misfit = np.any(np.nan_to_num(ratio) > COLOURED, axis=1)
    misfit |= np.any(np.nan_to_num(shift) > SHIFTED, axis=1)
    largest = np.max(np.nan_to_num(ar_ratio, nan=1.0), axis=1)
    widen = np.where(~misfit & (largest > WIDEN_FROM), np.sqrt(largest), 1.0)
    return Colour(misfit, ratio, shift, widen)


def widening(colour: Colour, white_std: bool) -> np.ndarray:
    """``[N]`` the factor a method's std is widened by: :attr:`Colour.widen` for a
    std that assumes white noise (``white_std``, the method's
    :attr:`~jaxcal.calibrators.methods.protocol.Method.white_std`), 1 for least
    squares, whose online check against its own later estimates already scales its
    std to the errors it makes (widened, it would be too wide)."""
    if white_std:
        return colour.widen
    return np.ones_like(colour.widen)


def misfit_rows(
    unit: np.ndarray, time: np.ndarray, z: np.ndarray, used: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(misfit [N], ratio [N, S])`` of :func:`colour_rows` (the flag and the
    Bartlett ratio per output)."""
    colour = colour_rows(unit, time, z, used)
    return colour.misfit, colour.ratio


def misfit_note(
    ratio: np.ndarray, unit: np.ndarray, outputs, *, withheld: bool = False,
    shift: np.ndarray | None = None,
) -> list[str]:  # fmt: skip
    """The console line when :func:`colour_rows` flagged a unit (else nothing);
    ``withheld``: the caller left those rows' std out; ``shift``: the CUSUM
    statistics (a unit flagged by them alone is named for its shift)."""
    coloured = np.nan_to_num(ratio) > COLOURED
    shifted = np.zeros_like(coloured) if shift is None else np.nan_to_num(shift)
    shifted = shifted > SHIFTED
    if not (coloured.any() or shifted.any()):
        return []
    flagged = unit[(coloured | shifted).any(axis=1)]
    shown = f"unit{'s' if len(np.unique(flagged)) > 1 else ''} {units_shown(flagged)}"
    parts = [
        f"{name} {np.nanmax(ratio[coloured[:, s], s]):.3g}"
        for s, name in enumerate(outputs)
        if coloured[:, s].any()
    ]
    moved = [
        f"{name} {np.nanmax(shift[shifted[:, s], s]):.3g}"
        for s, name in enumerate(outputs)
        if shifted[:, s].any()
    ]
    found = []
    if parts:
        found.append(
            f"autocorrelated (long-run variance / variance: {', '.join(parts)}; "
            "white noise 1)"
        )
    if moved:
        found.append(
            f"shifted from some row on (CUSUM of the innovations, in stds: "
            f"{', '.join(moved)}; flagged past {SHIFTED:g}: a sensor bias or a "
            "change the model lacks, which the parameters then absorb)"
        )
    return [
        f"the one-step innovations of {shown} are {' and '.join(found)}; rows "
        "marked in result.misfit: the model misfits the data, the parameters drift "
        "faster than the filter's random walk follows, or an output is quantised, "
        "stuck or biased. theta_std would be far too small there: it assumes white "
        "noise, and a parameter that absorbs a misfit takes on a bias no residual "
        "shows"
        + (
            "; so it is withheld there (NaN; misfit='keep' reports it anyway)"
            if withheld
            else ""
        )
    ]


def widen_note(widen: np.ndarray, unit: np.ndarray) -> list[str]:
    """The console line when :func:`colour_rows` widened a unit's std (else
    nothing)."""
    widened = widen > 1
    if not widened.any():
        return []
    return [
        f"the measurement noise of units {units_shown(unit[widened])} is coloured "
        "(their one-step innovations fit an AR noise; no shift, no strong colour): "
        "theta_std widened by the square root of its long-run variance ratio (up "
        f"to x{np.max(widen):.3g}), since autocorrelated rows carry less "
        "information than the white noise the std assumes"
    ]
