"""Write a prognosis to a folder: ``rul.csv``, ``report.json``, ``report.md``, figures.

``rul.csv`` has exactly the columns ``unit, rul, rul_low, rul_high`` (one row per test
unit, in the test file's unit order), the file a maintenance planner or a benchmark
scorer reads. ``report.json`` holds everything the numbers came from: the config, the
sources, the degradation model (:meth:`DegradationModel.to_json`), the held-out noise
check, the stage timings, the notes, a row per unit (age, RUL and interval, the driving
parameter and its share of samples, the censored share) and, with the truth, the
:func:`~jaxcal.prognosis.score.score` and each unit's true RUL. ``report.md`` is the
readable page (:mod:`jaxcal.prognosis.markdown`); ``units/unit_<id>.png`` draws each
unit (its calibrated trajectory of every deciding parameter, the posterior trend band,
the failure boundary and the predicted crossing) and ``rul.png`` the fleet. A
host-only leaf: every file goes through the one atomic writer
(:func:`jaxcal.runs.atomic.write_atomic`).

The result is read by attribute (``prediction``, ``model``, ``train``, ``test``,
``noise_check``, ``timings``, ``notes``), so any object of that shape will do.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time

import numpy as np
from matplotlib.figure import Figure

from jaxcal.diagnosis.report.write import json_safe
from jaxcal.plotting import save_figure
from jaxcal.prognosis.markdown import UNITS_DIR, render_markdown
from jaxcal.prognosis.score import score
from jaxcal.progress import progress_bar
from jaxcal.runs.atomic import write_atomic
from jaxcal.settings import config_to_dict

CSV_COLUMNS = ("unit", "rul", "rul_low", "rul_high")
FLEET_TOP = 1.4  # the fleet figure's axes end at this many times the largest RUL


def unit_label(unit) -> str:
    """A unit id as text: ``7`` for 7 and 7.0, the id itself otherwise."""
    value = unit.item() if isinstance(unit, np.generic) else unit
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def unit_rows(prediction, truth=None) -> list[dict]:
    """One dict per test unit: ``unit, now, rul, low, high, driver, driver_share,
    censored`` (and ``truth``, ``error`` = rul - truth, with ``truth [U]``)."""
    p = prediction
    rows = []
    for u in range(len(p.unit)):
        row = {
            "unit": unit_label(p.unit[u]),
            "now": float(p.now[u]),
            "rul": float(p.rul[u]),
            "low": float(p.rul_low[u]),
            "high": float(p.rul_high[u]),
            "driver": p.driver[u],
            "driver_share": float(p.driver_share[u]),
            "censored": float(p.censored[u]),
        }
        if truth is not None:
            row["truth"] = float(truth[u])
            row["error"] = row["rul"] - row["truth"]
        rows.append(row)
    return rows


def rul_csv(prediction) -> str:
    """The text of ``rul.csv`` (RULs in cycles to 0.01: finer than any data's clock)."""
    lines = [",".join(CSV_COLUMNS)]
    for u, unit in enumerate(prediction.unit):
        values = (prediction.rul[u], prediction.rul_low[u], prediction.rul_high[u])
        lines.append(",".join([unit_label(unit), *(f"{v:.2f}" for v in values)]))
    return "\n".join(lines) + "\n"


def report_dict(result, *, truth=None, source=None, config=None) -> dict:
    """The content of ``report.json`` (see the module docstring), JSON-safe."""
    p = result.prediction
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = config_to_dict(config)
    rep = {
        "config": config,
        "sources": source,
        "coverage": float(p.coverage),
        "samples": int(np.shape(p.samples)[1]),
        "training_units": int(len(result.train.unit)),
        "test_units": int(len(p.unit)),
        "model": result.model.to_json(),
        "noise_check": result.noise_check,
        "timings": dict(result.timings),
        "notes": list(result.notes),
        "units": unit_rows(p, truth),
    }
    if truth is not None:
        rep["score"] = score(p.rul, p.rul_low, p.rul_high, truth, p.samples)
    return json_safe(rep)


def plot_unit(fig: Figure, path: str, result, u: int, truth=None) -> str:
    """Draw test unit ``u`` into ``fig`` (cleared first, so one figure serves every
    unit) and save it to ``path``: per deciding parameter its calibrated trajectory,
    the posterior trend band, the boundary +- its spread and the predicted crossing
    with its interval; the true end of life when ``truth`` (its RUL) is given."""
    p, model, test = result.prediction, result.model, result.test
    fig.clf()  # which also resets the margins: fixed ones (in inches) set again, not
    # a constrained layout, which would cost a third more time over hundreds of units
    height = fig.get_figheight()
    fig.subplots_adjust(left=0.11, right=0.97, top=1 - 0.45 / height,
                        bottom=0.62 / height, hspace=0.66 / height)  # fmt: skip
    decide = [n for n, d in zip(model.names, model.decides, strict=True) if d]
    axes = np.atleast_1d(fig.subplots(len(decide), 1, sharex=True, squeeze=False))
    now, rul = float(p.now[u]), float(p.rul[u])
    end = now + float(p.rul_high[u])
    if truth is not None:
        end = max(end, now + float(truth))
    # the test trajectories may list the units in another order than the prediction
    row = [unit_label(x) for x in test.unit].index(unit_label(p.unit[u]))
    t_band = p.trend_time[u]
    right = min(float(t_band[-1]), end + 0.15 * (end - float(t_band[0])))
    shown = t_band <= right
    mask = test.mask[row]
    for ax, name in zip(axes.ravel(), decide, strict=True):
        k, j = list(p.names).index(name), list(test.names).index(name)
        b = list(model.names).index(name)
        low, mid, high = p.trend[u, k]
        ax.fill_between(
            t_band[shown],
            low[shown],
            high[shown],
            color="C0",
            alpha=0.2,
            lw=0,
            label=f"trend {p.coverage:.0%} band",
        )
        ax.plot(t_band[shown], mid[shown], color="C0", lw=1.2, label="trend median")
        ax.plot(
            test.time[row, mask],
            test.theta[row, mask, j],
            ".",
            ms=3,
            color="k",
            label="calibrated",
        )
        bound, spread = float(model.boundary[b]), float(model.boundary_std[b])
        ax.axhline(bound, color="C3", lw=1.2, label="failure boundary")
        if spread > 0:
            ax.axhspan(bound - spread, bound + spread, color="C3", alpha=0.12, lw=0)
        ax.axvspan(
            now + float(p.rul_low[u]),
            now + float(p.rul_high[u]),
            color="C1",
            alpha=0.2,
            lw=0,
        )
        ax.axvline(now + rul, color="C1", lw=1.5, label="predicted end")
        ax.axvline(now, color="0.5", lw=0.8, ls=":", label="now")
        if truth is not None:
            ax.axvline(
                now + float(truth), color="C2", lw=1.5, ls="--", label="true end"
            )
        ax.set_ylabel(name)
    axes.ravel()[0].legend(fontsize=7, loc="best", ncols=2)
    axes.ravel()[-1].set_xlabel("time (cycles)")
    title = f"unit {unit_label(p.unit[u])}: RUL {rul:.0f} [{p.rul_low[u]:.0f}, "
    title += f"{p.rul_high[u]:.0f}]" + ("" if truth is None else f", true {truth:.0f}")
    fig.suptitle(title + f"; driver {p.driver[u]}", fontsize=10)
    return save_figure(fig, path, dpi=90)


def plot_fleet(path: str, prediction, truth=None) -> str:
    """Predicted vs true RUL with interval bars, or (no truth) the RULs sorted."""
    p = prediction
    fig = Figure(
        figsize=(6.0, 5.0) if truth is not None else (8.0, 4.0), layout="constrained"
    )
    ax = fig.subplots()
    bars = np.stack([p.rul - p.rul_low, p.rul_high - p.rul])
    if truth is not None:
        hit = (truth >= p.rul_low) & (truth <= p.rul_high)
        for inside, color, label in (
            (True, "C0", "true RUL inside"),
            (False, "C3", "outside"),
        ):
            sel = hit == inside
            ax.errorbar(
                truth[sel],
                p.rul[sel],
                yerr=bars[:, sel],
                fmt="o",
                ms=3,
                color=color,
                elinewidth=0.7,
                alpha=0.8,
                label=label,
            )
        top = FLEET_TOP * float(max(truth.max(), p.rul.max()))
        ax.plot([0, top], [0, top], color="0.4", lw=1, ls="--")
        ax.set_xlim(0, top)
        ax.set_xlabel("true RUL (cycles)")
        ax.legend(fontsize=8)
    else:
        order = np.argsort(p.rul)
        ax.errorbar(
            np.arange(order.size),
            p.rul[order],
            yerr=bars[:, order],
            fmt="o",
            ms=3,
            elinewidth=0.7,
        )
        ax.set_xlabel("test units, sorted by predicted RUL")
        top = FLEET_TOP * float(p.rul.max())
    # a censored interval reaches the horizon: the axis stops short of it (said)
    clipped = int((p.rul_high > top).sum())
    ax.set_ylim(0, top)
    if clipped:
        ax.set_title(f"{clipped} interval(s) reach above the plot", fontsize=9)
    ax.set_ylabel(f"predicted RUL, {p.coverage:.0%} interval (cycles)")
    return save_figure(fig, path)


def write_prognosis(
    out,
    result,
    *,
    truth=None,
    source=None,
    config=None,
    progress: bool = True,
    unit_figures=None,
) -> dict:
    """Write ``rul.csv``, ``report.json``, ``report.md`` and the figures into ``out``.

    Args:
        out: the folder (created).
        result: a :class:`~jaxcal.prognosis.pipeline.Prognosis` (or the same shape).
        truth: ``[U]`` true RULs in the test units' order, or None.
        source: what the data came from (``{"train": path, "test": path, ...}``).
        config: the run's settings (a dataclass or a dict), stored as given.
        progress: a progress line on stderr while the unit figures are drawn.
        unit_figures: the units (ids) to draw a figure of; None: every unit. Unit
            figures of an earlier run in ``out`` that this run does not draw are
            removed.

    Returns:
        The report dict (as in ``report.json``, with ``figures`` and ``out``).
    """
    start = time.time()
    p = result.prediction
    if truth is not None:
        truth = np.asarray(truth, np.float64)
    rep = report_dict(result, truth=truth, source=source, config=config)
    os.makedirs(os.path.join(out, UNITS_DIR), exist_ok=True)
    write_atomic(os.path.join(out, "rul.csv"), rul_csv(p))
    plot_fleet(os.path.join(out, "rul.png"), p, truth)
    height = 1.1 + 2.2 * int(np.sum(result.model.decides))
    fig = Figure(figsize=(7.0, height))
    units = {}
    wanted = None if unit_figures is None else {unit_label(u) for u in unit_figures}
    drawn = [
        u
        for u in range(len(p.unit))
        if wanted is None or unit_label(p.unit[u]) in wanted
    ]
    bar = progress_bar(drawn, desc="prognosis plots", leave=False, disable=not progress)
    for u in bar:
        name = f"unit_{unit_label(p.unit[u])}.png"
        t_u = None if truth is None else truth[u]
        plot_unit(fig, os.path.join(out, UNITS_DIR, name), result, u, t_u)
        units[unit_label(p.unit[u])] = f"{UNITS_DIR}/{name}"
    bar.close()
    # a unit figure of an earlier run into the same folder would pass for this one's
    kept = {os.path.basename(v) for v in units.values()}
    for name in os.listdir(os.path.join(out, UNITS_DIR)):
        if name.startswith("unit_") and name.endswith(".png") and name not in kept:
            os.remove(os.path.join(out, UNITS_DIR, name))
    rep["figures"] = {"fleet": "rul.png", "units": units}
    rep["timings"]["report"] = time.time() - start
    write_atomic(os.path.join(out, "report.json"), json.dumps(rep, indent=2) + "\n")
    write_atomic(os.path.join(out, "report.md"), render_markdown(rep))
    return {**rep, "out": out}
