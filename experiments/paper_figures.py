"""Figures of ``experiments/paper.py``: the traces each evaluation keeps, and the PNGs.

:func:`save_traces` stores what the figures need from one evaluation (the stacked theta
traces, downsampled to at most 20,000 points, and four sensors of the first test unit)
as ``.npz``; :func:`make_figures` draws the paper's figures from them with
:func:`jaxcal.plotting.plot_stacked_traces`: theta inferred against the truth with the
test units stacked one after the other, per method (Fig. "Inference_Comp", and
"RSAC" for LAC); the tracking of four sensors (Fig. "Tracking Result"); the model-bias
case (Fig. "Inf_Comp_bias"); the four turbine modifiers of Dataset #2
(Fig. "Inference_AGT30").
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
from paper_presets import ALL_METHODS

MAX_POINTS = 20_000  # points per stacked trace kept for the figures
TRACK_WINDOW = 500  # samples of the first test unit in the tracking figure
TRACK_SENSORS = ("T30", "T48", "Ps30", "Nc")  # preferred four sensors


def save_traces(path: Path, run, units, suite) -> None:
    """The figure data of one evaluation, downsampled, as ``.npz`` (atomically)."""
    from jaxcal.paper.compare import stacked
    from jaxcal.runs.folder import write_atomic

    theta, starts = stacked(run.theta, units.mask)
    truth, _ = stacked(units.theta, units.mask)
    stride = max(1, math.ceil(len(theta) / MAX_POINTS))
    sensors = list(suite.problem.output_names)
    chosen = [s for s in TRACK_SENSORS if s in sensors]
    chosen += [s for s in sensors if s not in chosen][: 4 - len(chosen)]
    cols = [sensors.index(s) for s in chosen]
    window = min(TRACK_WINDOW, int(units.lengths[0]))
    buf = io.BytesIO()
    np.savez(
        buf,
        theta=theta[::stride].astype(np.float32),
        truth=truth[::stride].astype(np.float32),
        starts=starts / stride,
        stride=stride,
        theta_names=np.array(suite.problem.theta_names),
        x=units.x[0, :window][:, cols],
        xhat=run.xhat[0, :window][:, cols],
        sensors=np.array(chosen),
    )
    write_atomic(path, buf.getvalue())


def make_figures(out: Path, scalability: tuple[str, ...]) -> dict:
    """The paper's figures from the traces under ``out/traces``.

    Returns:
        ``{"figures": {file name: path}}`` of the PNGs written to ``out/figures``.
    """
    from jaxcal.plotting import plot_stacked_traces

    def load(name: str):
        path = out / "traces" / f"{name}.npz"
        return dict(np.load(path)) if path.is_file() else None

    figures = {}

    def draw(file: str, traces: dict, title: str, *, what: str = "theta") -> None:
        traces = {k: v for k, v in traces.items() if v is not None}
        if not traces:
            return
        first = next(iter(traces.values()))
        if what == "theta":
            series = {k: v["theta"] for k, v in traces.items()}
            truth, names = first["truth"], [str(n) for n in first["theta_names"]]
            bounds = first["starts"][1:]
            xlabel = f"sample (test units stacked, every {int(first['stride'])})"
        else:  # tracking: model output of each method against the measurement
            series = {k: v["xhat"] for k, v in traces.items()}
            truth, names = first["x"], [str(n) for n in first["sensors"]]
            bounds, xlabel = None, "sample of the first test unit"
            if what == "tracking error":  # x-hat - x: at full scale the dots hide it
                series = {k: v["xhat"] - v["x"] for k, v in traces.items()}
                truth = np.zeros_like(truth)
                names = [f"{n} error" for n in names]
        path = out / "figures" / file
        plot_stacked_traces(
            path, series, truth, bounds, names=names, xlabel=xlabel, title=title,
            truth_line=what != "theta",
        )  # fmt: skip
        figures[file] = str(path)

    for method in ALL_METHODS:
        draw(
            f"theta_ds1_{method}.png",
            {method: load(f"eval-ds1-{method}-clean")},
            f"Dataset #1: inferred ({method}) and true theta",
        )
    both = ("CLAC", "UKF")
    draw(
        "tracking_ds1.png",
        {m: load(f"eval-ds1-{m}-clean") for m in both},
        "Dataset #1: tracking of four sensors (truth: the measurement x)",
        what="tracking",
    )
    draw(
        "tracking_error_ds1.png",
        {m: load(f"eval-ds1-{m}-clean") for m in both},
        "Dataset #1: tracking error x-hat - x of four sensors (sensor units)",
        what="tracking error",
    )
    draw(
        "theta_ds1_bias.png",
        {m: load(f"eval-ds1-{m}-bias") for m in both},
        "Dataset #1 with model bias F x 1.02",
    )
    draw(  # the feedback follows the biased F, the gate hands over to CLAC
        "theta_ds1_bias_gate.png",
        {m: load(f"eval-ds1-{m}-bias") for m in ("UKF", "CLAC-inc", "CLAC-gate")},
        "Dataset #1 with model bias F x 1.02: CLAC-inc and CLAC-gate",
    )
    draw(
        "theta_ds2.png",
        {m: load(f"eval-ds2-{m}-clean") for m in both},
        "Dataset #2: four turbine modifiers",
    )
    for key in scalability:
        draw(
            f"theta_{key}.png",
            {m: load(f"eval-{key}-{m}-clean") for m in both},
            f"Dataset #2 variant {key}",
        )
    return {"figures": figures}
