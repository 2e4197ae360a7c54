"""Figures of the data sets and of calibration traces (host-only leaf, matplotlib Agg).

Every function takes numpy-convertible arrays and draws on a fresh ``Figure`` with an
Agg canvas (no pyplot: no global state, no display needed); the ``plot_*`` ones write a
PNG atomically (a temporary file in the target directory, then ``os.replace``), the
``*_figure`` ones return the figure. Nothing in the core imports this module at import
time.

* :func:`plot_flight_profiles`: alt / Mach / TRA against time (paper Fig. 2, left).
* :func:`plot_health_trajectories`: fleet health modifiers against cycle (Fig. 2,
  right).
* :func:`plot_stacked_traces`: theta traces of several units stacked one after the
  other, inferred against truth (the paper's inference figures).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from jaxcal.runs.atomic import write_atomic_with

TRUTH_COLOR = "tab:orange"  # the paper draws ground truth as orange squares
SERIES_COLORS = ("tab:blue", "tab:green", "tab:red", "tab:purple", "tab:brown")
_PROFILE_PANELS = ((0, "alt [kft]", 1e-3), (1, "Mach [-]", 1.0), (2, "TRA [%]", 1.0))


def save_figure(fig: Figure, path: str | os.PathLike, *, dpi: int = 120) -> str:
    """Write ``fig`` as PNG to ``path`` atomically (temp file + rename); return path."""
    FigureCanvasAgg(fig)
    write_atomic_with(path, lambda f: fig.savefig(f, format="png", dpi=dpi))
    return os.fspath(path)


def _batched(x, name: str, ndim: int) -> np.ndarray:
    """``x`` as a float array with a leading batch axis of ``ndim`` total dims."""
    x = np.asarray(x, dtype=float)
    if x.ndim == ndim - 1:
        x = x[None]
    if x.ndim != ndim:
        raise ValueError(f"{name} must have {ndim - 1} or {ndim} dims, got {x.shape}")
    return x


def plot_flight_profiles(
    path,
    t,
    w,
    *,
    mask=None,
    labels: Sequence[str] | None = None,
    title: str | None = None,
    dpi: int = 120,
) -> str:
    """Altitude, Mach and TRA against time, one line per flight.

    Args:
        path: output PNG.
        t: [T] or [F, T] time [s].
        w: [T, 4] or [F, T, 4] conditions (alt [ft], Mach, TRA [%], T2), as
            CONDITION_NAMES.
        mask: optional [T] or [F, T] validity (padded samples are not drawn).
        labels: optional F legend labels.
        title: optional figure title.
        dpi: resolution.

    Returns:
        The written path.
    """
    w = _batched(w, "w", 3)
    num_flights, num_steps = w.shape[:2]
    t = np.broadcast_to(_batched(t, "t", 2), (num_flights, num_steps))
    if w.shape[-1] < 3:
        raise ValueError(f"w needs >= 3 columns (alt, Mach, TRA), got {w.shape}")
    valid = np.ones(w.shape[:2], bool) if mask is None else _batched(mask, "mask", 2)
    valid = np.broadcast_to(valid.astype(bool), w.shape[:2])
    if labels is not None and len(labels) != num_flights:
        raise ValueError(f"labels needs {num_flights} entries, got {len(labels)}")
    fig = Figure(figsize=(12, 3.4), layout="constrained")
    axes = fig.subplots(1, len(_PROFILE_PANELS), sharex=True)
    for ax, (col, ylabel, scale) in zip(axes, _PROFILE_PANELS, strict=True):
        for i in range(num_flights):
            label = None if labels is None else labels[i]
            ax.plot(
                t[i][valid[i]] / 60.0,
                w[i, :, col][valid[i]] * scale,
                lw=0.8,
                label=label,
            )
        ax.set_xlabel("time [min]")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    if labels is not None:
        axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi=dpi)


def plot_health_trajectories(
    path,
    cycles,
    theta,
    names: Sequence[str],
    *,
    mask=None,
    select: Sequence[str] | None = None,
    onset=None,
    unit_labels: Sequence[str] | None = None,
    title: str | None = None,
    dpi: int = 120,
) -> str:
    """Health modifiers of a fleet against flight cycle, one panel per modifier.

    Args:
        path: output PNG.
        cycles: [C] or [U, C] cycle numbers.
        theta: [C, P] or [U, C, P] modifiers, columns named by ``names``.
        names: P column names.
        mask: optional [U, C] validity (cycles after end of life are not drawn).
        select: names to draw; default: the columns that move in at least one unit.
        onset: optional [U] abnormal-onset cycles t_s, marked on each line.
        unit_labels: optional U legend labels (default "unit 1", ...).
        title: optional figure title.
        dpi: resolution.

    Returns:
        The written path.
    """
    theta = _batched(theta, "theta", 3)
    num_units, num_cycles, num_params = theta.shape
    if len(names) != num_params:
        raise ValueError(f"names needs {num_params} entries, got {len(names)}")
    cycles = np.broadcast_to(_batched(cycles, "cycles", 2), (num_units, num_cycles))
    valid = np.ones((num_units, num_cycles), bool) if mask is None else mask
    valid = np.broadcast_to(_batched(valid, "mask", 2).astype(bool), cycles.shape)
    if select is None:
        values = theta[valid]  # [valid cycles, P]
        moving = [
            n for j, n in enumerate(names) if values.size and np.ptp(values[:, j])
        ]
        select = moving or list(names)
    unknown = [n for n in select if n not in names]
    if unknown:
        raise ValueError(f"select has unknown name(s) {unknown}; names are {names}")
    labels = unit_labels or [f"unit {u + 1}" for u in range(num_units)]
    fig = Figure(figsize=(5.5 * len(select), 4.0), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(select)))
    for ax, name in zip(axes, select, strict=True):
        j = list(names).index(name)
        for u in range(num_units):
            c, y = cycles[u][valid[u]], theta[u, :, j][valid[u]]
            (line,) = ax.plot(c, y, lw=1.0, marker=".", ms=3, label=labels[u])
            if onset is not None:
                k = np.searchsorted(c, np.asarray(onset)[u])
                if k < c.size:
                    ax.plot(c[k], y[k], "o", color=line.get_color(), mfc="none", ms=7)
        ax.set_xlabel("time [flight cycles]")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=2)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi=dpi)


def plot_stacked_traces(
    path,
    series: Mapping[str, np.ndarray],
    truth=None,
    unit_boundaries=None,
    *,
    names: Sequence[str] | None = None,
    max_points: int = 20_000,
    xlabel: str = "sample (units stacked)",
    title: str | None = None,
    truth_line: bool = False,
    dpi: int = 120,
) -> str:
    """Traces of one or more estimates (and the truth), units stacked in one sequence.

    Args:
        path: output PNG.
        series: label -> [N] or [N, P] estimates (e.g. {"CLAC": theta_hat}).
        truth: optional [N] or [N, P] ground truth, drawn as orange squares.
        unit_boundaries: optional sample indices where a new unit starts (dotted lines).
        names: optional P panel names (y labels).
        max_points: draw at most about this many points per trace (uniform stride).
        xlabel: x-axis label.
        title: optional figure title.
        truth_line: draw the truth as a solid line beneath the estimates (the
            paper's tracking figure) instead of squares above them.
        dpi: resolution.

    Returns:
        The written path.
    """
    if not series and truth is None:
        raise ValueError("plot_stacked_traces needs at least one series or the truth")
    if truth is not None and "truth" in series:
        raise ValueError('series label "truth" is reserved for the truth argument')
    arrays = {str(k): np.asarray(v, dtype=float) for k, v in series.items()}
    if truth is not None:
        arrays["truth"] = np.asarray(truth, dtype=float)
    arrays = {k: (v[:, None] if v.ndim == 1 else v) for k, v in arrays.items()}
    shapes = {v.shape for v in arrays.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        got = {k: v.shape for k, v in arrays.items()}
        raise ValueError(f"series and truth must be [N] or the same [N, P]; got {got}")
    num_samples, num_params = next(iter(shapes))
    if names is not None and len(names) != num_params:
        raise ValueError(f"names needs {num_params} entries, got {len(names)}")
    stride = max(1, math.ceil(num_samples / max_points))
    index = np.arange(0, num_samples, stride)
    fig = Figure(figsize=(12, 2.6 * num_params + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(num_params, 1, sharex=True))
    for j, ax in enumerate(axes):
        if truth is not None:
            truth_j = arrays["truth"][index, j]
            if truth_line:  # beneath: an estimate on top of the truth stays visible
                ax.plot(
                    index, truth_j, "-", color=TRUTH_COLOR, lw=1.2, zorder=1,
                    label="truth",
                )  # fmt: skip
            else:  # drawn above the estimates so that the truth stays visible
                ax.plot(
                    index, truth_j, "s", color=TRUTH_COLOR, ms=2.0, zorder=3,
                    label="truth",
                )  # fmt: skip
        for k, label in enumerate(str(s) for s in series):
            color = SERIES_COLORS[k % len(SERIES_COLORS)]
            ax.plot(
                index, arrays[label][index, j], "o", ms=1.5, color=color, label=label
            )
        for b in [] if unit_boundaries is None else np.asarray(unit_boundaries):
            ax.axvline(b, color="0.5", lw=0.6, ls=":")
        ax.set_ylabel(names[j] if names is not None else f"theta[{j}]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, markerscale=3, loc="best")
    axes[-1].set_xlabel(xlabel)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi=dpi)


def _units_to_draw(units, present: np.ndarray, dtype, max_units: int) -> np.ndarray:
    """The requested unit ids (each must be ``present``), or the first
    ``max_units`` present ones."""
    if units is None:
        return present[:max_units]
    units = np.asarray(units, dtype=dtype).reshape(-1)
    missing = [u for u in units.tolist() if u not in set(present.tolist())]
    if missing:
        raise ValueError(f"unit(s) {missing} not in the result: {present.tolist()}")
    return units


def unit_traces_figure(
    time,
    unit,
    theta,
    names: Sequence[str],
    *,
    theta_std=None,
    valid=None,
    units: Sequence | None = None,
    max_units: int = 6,
    ylabels: Sequence[str] | None = None,
    title: str | None = None,
) -> Figure:
    """Calibrated parameters against time, one panel per parameter, a line per unit.

    Rows are drawn in time order within their unit; where ``theta_std`` is given a
    band of ±2 std surrounds the line, and skipped rows (``valid`` False, which
    repeat the unit's last estimate) are marked with crosses.

    Args:
        time: [N] row time.
        unit: [N] row unit id.
        theta: [N, P] estimates, columns named by ``names``.
        names: P parameter names.
        theta_std: optional [N, P] standard deviation of ``theta``.
        valid: optional [N] bool, False where the row was skipped.
        units: the unit ids to draw (default: the first ``max_units`` in sorted order).
        max_units: how many units to draw when ``units`` is not given.
        ylabels: optional P y-axis labels (default: ``names``).
        title: optional figure title.

    Returns:
        The ``Figure`` (Agg canvas attached: ``fig.savefig(path)`` works).
    """
    theta = _batched(theta, "theta", 2)
    num_rows, num_params = theta.shape
    if len(names) != num_params:
        raise ValueError(f"names needs {num_params} entries, got {len(names)}")
    time, unit = np.asarray(time), np.asarray(unit)
    if time.shape != (num_rows,) or unit.shape != (num_rows,):
        raise ValueError(
            f"time and unit must be [{num_rows}]: {time.shape}, {unit.shape}"
        )
    std = None if theta_std is None else np.asarray(theta_std, dtype=float)
    if std is not None and std.shape != theta.shape:
        raise ValueError(f"theta_std must be {theta.shape}, got {std.shape}")
    ok = np.ones(num_rows, bool) if valid is None else np.asarray(valid, bool)
    present = np.unique(unit)
    units = _units_to_draw(units, present, unit.dtype, max_units)
    fig = Figure(figsize=(10, 2.4 * num_params + 0.8), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(num_params, 1, sharex=True, squeeze=False)[:, 0]
    for k, u in enumerate(units):
        rows = np.flatnonzero(unit == u)
        rows = rows[np.argsort(time[rows], kind="stable")]
        t, skipped, color = time[rows], ~ok[rows], f"C{k % 10}"
        for j, ax in enumerate(axes):
            y = theta[rows, j]
            ax.plot(t, y, lw=1.0, color=color, label=f"unit {u}")
            if std is not None:
                s = std[rows, j]
                ax.fill_between(t, y - 2 * s, y + 2 * s, color=color, alpha=0.2, lw=0)
            if skipped.any():
                ax.plot(t[skipped], y[skipped], "x", color=color, ms=5)
    for j, ax in enumerate(axes):
        ax.set_ylabel(names[j] if ylabels is None else ylabels[j])
        ax.grid(alpha=0.3)
    if not ok.all():  # one legend entry for the crosses of every unit
        axes[0].plot([], [], "x", color="0.3", label="skipped")
    shown = "" if len(units) == len(present) else f" ({len(units)} of {len(present)})"
    band = "" if std is None else ", band ±2 std"
    axes[0].legend(fontsize=8, ncol=2, loc="best", title=f"units{shown}{band}")
    axes[-1].set_xlabel("time")
    if title:
        fig.suptitle(title)
    return fig
