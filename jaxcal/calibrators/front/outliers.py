"""Robust noise scale and per-row outlier flags from a residual (host-side numpy).

One wild reading must not decide the noise level of every unit: a mean of squares
has a breakdown point of zero (one value of 1e6 sets it), the median absolute
deviation one of 50 %. The statistics here are the textbook robust ones:

* :func:`robust_scale`: the normalised MAD, ``1.4826 median|r - median r|`` per
  column, a consistent estimate of a Gaussian std (Hampel 1974, "The influence curve
  and its role in robust estimation", JASA 69; Rousseeuw & Croux 1993, "Alternatives
  to the median absolute deviation", JASA 88).
* :func:`robust_noise`: that MAD as a first scale, values farther than ``threshold``
  of it from the median rejected, then the root mean square of the rest: the hard
  rejection ("skipped") estimator of Hampel et al. (1986, "Robust Statistics: the
  approach based on influence functions", sec. 1.4, the X84 rule), which keeps the
  efficiency of the mean square on Gaussian data and the breakdown of the MAD.
* :func:`outlier_rows`: a row is an outlier when one of its standardised residuals
  ``|z| = |r| / scale`` exceeds ``threshold`` (:data:`OUTLIER_Z` = 6: a Gaussian
  value does so with probability 2e-9, about once in 10^8 rows of 5 outputs, so
  clean data are not flagged, while a reading off by orders of magnitude always is).

* :func:`stuck_runs`: runs of at least :data:`STUCK_RUN` identical readings of one
  output in a unit, on an output whose readings otherwise change from row to row (a
  quantised output, which repeats most of its values, has none): a sensor that
  froze, or a logger that repeats its last value.

The residual is whatever the caller standardises: the front door
(:mod:`jaxcal.calibrators.front.screen`) passes the UKF's innovation over its predicted
std, the diagnosis a fit's residual over the noise. Shapes: ``N`` rows, ``S``
outputs.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

STUCK_RUN = 8  # identical readings in a row that make a stuck sensor
QUANTISED = 0.5  # an output repeating more of its readings than this is quantised
OUTLIER_Z = 6.0  # |standardised residual| beyond which a reading is an outlier
MAD_TO_STD = 1.4826  # 1 / Phi^-1(3/4): the MAD of a Gaussian is 0.6745 std


def robust_scale(resid: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """``[S]`` normalised MAD of each column over the kept, finite rows.

    Args:
        resid: ``[N, S]``.
        keep: ``[N]`` bool rows to use (default all); non-finite values are left out.

    Returns:
        ``[S]`` scale (``nan`` for a column without a finite kept value).
    """
    resid = _kept(resid, keep)
    return MAD_TO_STD * _median(np.abs(resid - _median(resid)))


def robust_centre(resid: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """``[S]`` median of each column over the kept, finite rows (``nan`` if none)."""
    return _median(_kept(resid, keep))


def robust_noise(
    resid: np.ndarray,
    keep: np.ndarray | None = None,
    threshold: float = OUTLIER_Z,
) -> np.ndarray:
    """``[S]`` root mean square of each column after rejecting values farther than
    ``threshold`` MAD-scales from its median (module docstring).

    Args:
        resid: ``[N, S]`` residual in output units.
        keep: ``[N]`` bool rows to use (default all); non-finite values are left out.
        threshold: rejection distance in units of :func:`robust_scale`.

    Returns:
        ``[S]`` noise std (``nan`` for a column without a finite kept value; the
        plain root mean square where the MAD is 0, e.g. rounded readings).
    """
    resid = _kept(resid, keep)
    scale = robust_scale(resid)
    near = np.abs(resid - _median(resid)) <= threshold * scale
    near |= ~(scale > 0)  # no spread to judge by: keep every finite value
    inlier = np.where(near & np.isfinite(resid), resid, np.nan)
    with warnings.catch_warnings():  # an all-nan column is nan, said in the doc
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.sqrt(np.nanmean(inlier**2, axis=0))


class OutlierRows(NamedTuple):
    """What :func:`outlier_rows` found.

    Attributes:
        mask: ``[N]`` bool, True on an outlier row.
        z: ``[N, S]`` the standardised residual (``nan`` where not judged).
        worst: ``[N]`` int, the output with the largest ``|z|`` of each row.
    """

    mask: np.ndarray
    z: np.ndarray
    worst: np.ndarray


def outlier_rows(
    resid: np.ndarray,
    scale: np.ndarray | float = 1.0,
    keep: np.ndarray | None = None,
    threshold: float = OUTLIER_Z,
) -> OutlierRows:
    """Rows with a standardised residual ``|resid / scale|`` beyond ``threshold``.

    Args:
        resid: ``[N, S]`` residual.
        scale: its std, ``[S]`` per output or ``[N, S]`` per value (e.g. the noise,
            or a filter's predicted innovation std), or a scalar.
        keep: ``[N]`` bool rows that may be judged (default all); other rows and
            non-finite values are never flagged.
        threshold: ``|z|`` beyond which a value is an outlier.

    Returns:
        :class:`OutlierRows`.
    """
    resid = np.asarray(resid, np.float64)
    with np.errstate(all="ignore"):
        z = resid / np.asarray(scale, np.float64)
    judged = np.isfinite(z)
    if keep is not None:
        judged &= np.asarray(keep, bool)[:, None]
    z = np.where(judged, z, np.nan)
    size = np.where(judged, np.abs(z), -1.0)
    return OutlierRows(
        mask=np.any(size > threshold, axis=1), z=z, worst=np.argmax(size, axis=1)
    )


def describe_outliers(
    found: OutlierRows,
    unit: np.ndarray,
    output_names: Sequence[str],
    limit: int = 3,
) -> str:
    """One line: how many rows, in which units, which outputs, the largest ``|z|``.

    Args:
        found: from :func:`outlier_rows`.
        unit: ``[N]`` unit id of each row.
        output_names: ``S`` names.
        limit: units and outputs listed before "...".

    Returns:
        e.g. ``"3 outlier rows (units 2 (2), 5 (1); outputs temp (3); largest
        |z| 3.1e+07)"``, or ``""`` when there is none.
    """
    rows = np.flatnonzero(found.mask)
    if not rows.size:
        return ""

    def top(values, names=None):
        ids, counts = np.unique(values, return_counts=True)
        order = np.argsort(-counts, kind="stable")[:limit]
        label = (lambda i: names[i]) if names is not None else str
        more = ", ..." if len(ids) > limit else ""
        return ", ".join(f"{label(ids[i])} ({counts[i]})" for i in order) + more

    largest = float(np.nanmax(np.abs(found.z[rows])))
    return (
        f"{rows.size} outlier row{'s' * (rows.size > 1)} (units "
        f"{top(np.asarray(unit)[rows])}; outputs "
        f"{top(found.worst[rows], list(output_names))}; largest |z| {largest:.3g})"
    )


class StuckRun(NamedTuple):
    """One run of identical readings (:func:`stuck_runs`).

    Attributes:
        output: the output's column.
        unit: the unit id.
        rows: ``[k]`` the run's rows (positions in the data), in time order.
    """

    output: int
    unit: int
    rows: np.ndarray


def stuck_runs(
    x: np.ndarray, unit: np.ndarray, time: np.ndarray, min_run: int = STUCK_RUN
) -> list[StuckRun]:
    """Runs of at least ``min_run`` identical finite readings of one output within a
    unit (rows in time order), on outputs that are not quantised: an output whose
    readings outside the runs repeat the previous one more often than
    :data:`QUANTISED` (rounded readings, a setpoint) has no run.

    Args:
        x: ``[N, S]`` readings (``nan``: missing, never part of a run).
        unit, time: ``[N]`` the rows' unit and time.
        min_run: the shortest run that counts.

    Returns:
        The runs, by output then unit.
    """
    x = np.asarray(x, np.float64)
    order = np.lexsort((np.asarray(time), np.asarray(unit)))
    u, xs = np.asarray(unit)[order], x[order]
    same_unit = u[1:] == u[:-1]
    runs = []
    for s in range(x.shape[1]):
        col = xs[:, s]
        repeat = same_unit & (col[1:] == col[:-1])  # NaN never repeats
        # run starts: a row that does not repeat the one before it
        start = np.flatnonzero(np.concatenate([[True], ~repeat]))
        length = np.diff(np.concatenate([start, [len(col)]]))
        long = (length >= min_run) & np.isfinite(col[start])
        if not long.any():
            continue
        in_run = np.zeros(len(col), bool)
        for a, n in zip(start[long], length[long], strict=True):
            in_run[a : a + n] = True
        pairs = same_unit & ~in_run[1:] & np.isfinite(col[1:]) & np.isfinite(col[:-1])
        if pairs.sum() and (repeat & pairs).sum() / pairs.sum() > QUANTISED:
            continue
        runs += [
            StuckRun(s, int(u[a]), order[a : a + n])
            for a, n in zip(start[long], length[long], strict=True)
        ]
    return runs


def _median(values: np.ndarray) -> np.ndarray:
    """``[S]`` nan-median of each column (``nan`` for an empty or all-nan one)."""
    if not values.shape[0]:
        return np.full(values.shape[1:], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(values, axis=0)


def _kept(resid: np.ndarray, keep: np.ndarray | None) -> np.ndarray:
    resid = np.asarray(resid, np.float64)
    if resid.ndim != 2:
        raise ValueError(f"resid must be [N, S], got shape {resid.shape}")
    if keep is not None:
        resid = resid[np.asarray(keep, bool)]
    return np.where(np.isfinite(resid), resid, np.nan)
