"""Write a diagnosis as ``report.json``, ``report.md`` and PNG figures (host-only leaf).

The page's text is :mod:`jaxcal.diagnosis.report.markdown`; this module builds the JSON
and draws.

The JSON names the verdict, the identified effect(s) with their fitted sizes and
standard errors, the ranking with its evidence (LR statistic, log10 p, BIC and delta
BIC against the declared-only model), the confounded and absorbed candidates, the
discrepancy (what it depends on) and the errors before and after: tracking RMSE per
output in the model's units and in noise multiples, theta RMSE where the truth is known
and residual whiteness (Ljung–Box per output). Names and units are the model's
(:class:`~jaxcal.model.Model` conditions, parameters, outputs and effects). Every file
is written atomically.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
from matplotlib.figure import Figure
from scipy import stats as sps

from jaxcal.diagnosis.fitting.identify import Identification
from jaxcal.diagnosis.pipeline import DiagnosisResult, Stage
from jaxcal.diagnosis.report.extended import added_parameters, write_extended
from jaxcal.diagnosis.report.markdown import render_markdown
from jaxcal.diagnosis.report.units import units_json
from jaxcal.diagnosis.residuals.summaries import summary_table
from jaxcal.plotting import plot_stacked_traces, save_figure
from jaxcal.runs.atomic import write_atomic

MAX_RANKING = 20  # ranking rows written to the report


def write_text(path: str, text: str) -> str:
    """Write ``text`` to ``path`` atomically (``runs.atomic.write_atomic``)."""
    return str(write_atomic(path, text))


def json_safe(value):
    """JSON-safe copy of nested dicts / lists: numpy to Python, NaN / inf to None."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _ranking(ident: Identification) -> list[dict]:
    """Ranking rows; a candidate's sizes there are from its own screening refit, so
    they are named ``screen_sizes`` (the reported sizes are the final fit's, in
    ``identified``)."""
    out = []
    for e in ident.ranking[:MAX_RANKING]:
        row = e._asdict()
        row["members"] = [c.name for c in e.members]
        row["forms"] = [c.form for c in e.members]
        row["screen_sizes"], row["screen_stds"] = row.pop("sizes"), row.pop("stds")
        out.append(row)
    return out


def _noise(d) -> dict:
    """The noise model per output (level, AR colour, HAC inflation, whiteness)."""
    n = d.noise
    names = d.sensor_names
    return {
        "source": n.source,
        "std": dict(zip(names, n.sigma.tolist(), strict=True)),
        "ar_order": dict(zip(names, n.order.tolist(), strict=True)),
        "ar": {s: n.ar[j, : n.order[j]].tolist() for j, s in enumerate(names)},
        "inflation": dict(zip(names, n.inflation.tolist(), strict=True)),
        "whiteness_p": dict(zip(names, n.whiteness_p.tolist(), strict=True)),
    }


UNIT_TEST = (
    "{form}; one-sided minimum-effect z-test of H0: |size| <= {delta:.3g} ({share:g} "
    "of the effect's natural step) per unit, Holm step-down across the units at "
    "family-wise level {alpha:g}; a smoothly changing parameter's size is its change "
    "over the unit's record (last minus first cycle)"
)
FORM_TEXT = {
    "fleet": "fitted fleet-wide (one value), each unit tested on its own data",
    "units": "fitted in the units whose own data show it (chosen by the extended "
    "BIC), only those tested",
}
ONSET_RULE = (
    "step: the onset maximising the unit's likelihood, with its 95 % "
    "profile-likelihood interval; smooth parameter: first cycle from which its change "
    "since the first cycle stays beyond {delta:.3g} + {z:.2f} std (Bonferroni at "
    "{alpha:g} / units) to the unit's last cycle; drift: first cycle at which the "
    "accumulated change reaches one noise std of the sensor; constant form: the "
    "unit's first cycle"
)


def _identified(res: DiagnosisResult, alpha: float) -> list[dict]:
    """The added effects with their fleet and per-unit verdicts."""
    z = float(sps.norm.isf(alpha / max(res.data.num_units, 1)))
    out = []
    for entry, eff in zip(res.identified, res.unit_effects, strict=True):
        out.append(
            {
                **entry,
                "unit_test": UNIT_TEST.format(
                    alpha=alpha,
                    delta=eff.min_size,
                    form=FORM_TEXT[eff.form],
                    share=eff.min_effect,
                ),
                "onset_rule": ONSET_RULE.format(z=z, alpha=alpha, delta=eff.min_size),
                "min_size": eff.min_size,
                "units": units_json(eff, res.data.unit_ids),
            }
        )
    return out


def _stage(stage: Stage, names, condition_names) -> dict:
    return {
        "whiteness_p": dict(zip(names, stage.whiteness_p.tolist(), strict=True)),
        "tracking_rmse": dict(zip(names, stage.tracking_rmse.tolist(), strict=True)),
        "tracking_rmse_norm": dict(
            zip(names, stage.tracking_rmse_norm.tolist(), strict=True)
        ),
        "mean_tracking_rmse_norm": float(np.mean(stage.tracking_rmse_norm)),
        "theta_rmse": stage.theta_rmse,
        "whiteness": stage.whiteness,
        "ssr": stage.fit.ssr,
        "bic": stage.fit.bic,
        "num_params": stage.fit.num_params,
        "residuals": summary_table(stage.summary, names, condition_names),
    }


def report_dict(
    res: DiagnosisResult,
    *,
    source: str = "",
    model: str = "",
    truth: dict | None = None,
    config: dict | None = None,
) -> dict:
    """Everything of the diagnosis as a JSON-ready dict (``model``: its name)."""
    d = res.data
    alpha = res.alpha
    disc = None
    if res.discrepancy is not None:
        disc = [
            {
                **s._asdict(),
                "amplitude_units": s.amplitude * float(d.noise_std[j]),
                "mean_units": s.mean * float(d.noise_std[j]),
            }
            for j, s in enumerate(res.discrepancy.sensors)
            if s.significant
        ]
    out = {
        "source": source,
        "model": model,
        "declared": list(res.declared),
        "data": {
            "rows": d.num_rows,
            "units": d.num_units,
            "unit_ids": d.unit_ids.tolist(),
            "sensors": list(d.sensor_names),
            "units_of": {
                **dict(zip(d.condition_names, d.condition_units, strict=True)),
                **dict(zip(d.sensor_names, d.sensor_units, strict=True)),
            },
            "excluded": d.excluded,
            "noise_std": dict(zip(d.sensor_names, d.noise_std.tolist(), strict=True)),
            "noise_source": d.noise_source,
            "noise": _noise(d),
            "knots_per_unit": d.num_knots,
            "notes": list(d.notes),
            # rows with NaN / Inf, dropped before the fit: in total and per column
            "dropped": {"rows": d.dropped_rows, "columns": dict(d.dropped)},
        },
        "verdict": res.verdict,
        "flags": list(res.flags),
        "plausible": not res.flags,
        "identified": _identified(res, alpha),
        "fallback_note": res.fallback_note,
        "confounded": res.confounded,
        "absorbed": res.identification.absorbed,
        "added": res.added,
        "num_tests": res.identification.num_tests,
        "ranking": _ranking(res.identification),
        "ranking_with_discrepancy": None
        if res.rescreen is None
        else _ranking(res.rescreen),
        "discrepancy": disc,
        "before": _stage(res.before, d.sensor_names, d.condition_names),
        "after": _stage(res.after, d.sensor_names, d.condition_names),
        "truth": truth,
        "config": config,
        # wall seconds of each stage of the diagnosis (jaxcal.diagnosis.timing)
        "timings": dict(res.timings),
    }
    return json_safe(out)


def _sensor_axes(num_sensors: int, width: float, height: float):
    """A figure with one panel per output, three a row: ``(fig, axes [S])``."""
    cols = min(3, num_sensors)
    rows = math.ceil(num_sensors / cols)
    fig = Figure(figsize=(width * cols, height * rows + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax in axes[num_sensors:]:
        ax.set_visible(False)
    return fig, axes[:num_sensors]


def _stacked_residuals(path, res: DiagnosisResult) -> str:
    d = res.data
    fig, axes = _sensor_axes(d.num_sensors, 4.2, 2.2)
    stride = max(1, d.num_rows // 4000)
    idx = np.arange(0, d.num_rows, stride)
    for j, ax in enumerate(axes):
        pairs = (("before", res.before, "0.6"), ("after", res.after, "tab:blue"))
        for label, stage, color in pairs:
            resid = stage.fit.evaluation.resid[idx, j]
            ax.plot(idx, resid, ".", ms=1.5, color=color, label=label)
        for b in d.starts[1:-1]:
            ax.axvline(b, color="0.8", lw=0.5, ls=":")
        ax.set_title(f"{d.sensor_names[j]} [{d.sensor_units[j]}]", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, markerscale=4)
    fig.supxlabel("row (units stacked)")
    fig.supylabel("residual / noise std")
    return save_figure(fig, path)


def _explained(path, res: DiagnosisResult) -> str:
    """Before-residual against what the added terms explain, per sensor."""
    d = res.data
    before, after = res.before.fit.evaluation, res.after.fit.evaluation
    explained = (after.yhat - before.yhat) / d.noise_std
    fig, axes = _sensor_axes(d.num_sensors, 3.6, 3.0)
    idx = np.arange(0, d.num_rows, max(1, d.num_rows // 3000))
    for j, ax in enumerate(axes):
        ax.plot(explained[idx, j], before.resid[idx, j], ".", ms=2, alpha=0.5)
        lo = min(explained[:, j].min(), before.resid[:, j].min())
        hi = max(explained[:, j].max(), before.resid[:, j].max())
        ax.plot([lo, hi], [lo, hi], color="tab:red", lw=0.8)
        ax.set_title(d.sensor_names[j], fontsize=9)
        ax.grid(alpha=0.3)
    fig.supxlabel("change of the model output by the added terms / noise std")
    fig.supylabel("residual before / noise std")
    fig.suptitle(f"signature of {' + '.join(res.added) or 'nothing'} vs the residual")
    return save_figure(fig, path)


def _theta(path, res: DiagnosisResult) -> str:
    d = res.data
    names = list(res.after.fit.spec.unit_params)
    cols = [d.parameter_names.index(n) for n in names]
    series = {
        "before": res.before.fit.evaluation.theta[:, cols],
        "after": res.after.fit.evaluation.theta[:, cols],
    }
    truth = None
    if d.theta_true is not None and all(n in d.theta_names for n in names):
        truth = d.theta_true[:, [d.theta_names.index(n) for n in names]]
    return plot_stacked_traces(
        path,
        series,
        truth,
        d.starts[1:-1],
        names=names,
        title="calibrated parameters, units stacked",
    )


def _unit_map(path, res: DiagnosisResult) -> str | None:
    """Units x cycles heat map of each added effect, carriers and onsets marked."""
    if not res.unit_effects:
        return None
    d = res.data
    offset = d.cycle - d.cycle[d.starts[:-1]][d.unit]
    span = max(float(offset.max()), 1.0)
    cols = int(min(400, span + 1))
    col = np.minimum((offset / span * (cols - 1)).round().astype(int), cols - 1)
    n = len(res.unit_effects)
    fig = Figure(
        figsize=(9.0, 1.2 + n * min(0.05 * d.num_units + 1.5, 9.0)),
        layout="constrained",
    )
    axes = np.atleast_1d(fig.subplots(n, 1, squeeze=False)).ravel()
    by_name = {c.name: c for c in res.members}
    for ax, eff in zip(axes, res.unit_effects, strict=True):
        grid = np.full((d.num_units, cols), np.nan)
        grid[d.unit, col] = eff.trajectory
        vmax = float(np.nanpercentile(np.abs(grid), 98)) or 1.0
        im = ax.imshow(
            grid, aspect="auto", cmap="RdBu_r", vmin=-vmax, vmax=vmax,
            interpolation="nearest", extent=(0, span, d.num_units - 0.5, -0.5),
        )  # fmt: skip
        carriers = np.flatnonzero(eff.carries)
        first = d.cycle[d.starts[:-1]]
        ax.plot(
            eff.onset[carriers] - first[carriers], carriers, "k|", ms=4,
            label="onset (carriers)",
        )  # fmt: skip
        ax.plot(
            np.full(carriers.size, -0.01 * span), carriers, "k>", ms=3,
            clip_on=False, label="carries",
        )  # fmt: skip
        step = max(1, d.num_units // 30)
        ticks = np.arange(0, d.num_units, step)
        ax.set_yticks(ticks, [str(u) for u in d.unit_ids[ticks]], fontsize=6)
        ax.set_ylabel("unit")
        ax.set_title(
            f"{eff.name}: carried by {carriers.size} of {d.num_units} units",
            fontsize=9,
        )
        cand = by_name[eff.name]
        label = cand.unit  # a drift is drawn as its accumulated change
        if cand.kind.profile == "drift":
            label = "accumulated change " + cand.unit.split(" per ")[0]
        fig.colorbar(im, ax=ax, label=label, shrink=0.8)
        ax.legend(fontsize=6, loc="lower right")
    axes[-1].set_xlabel("cycles since the unit's first cycle")
    return save_figure(fig, path)


def write_report(
    out_dir: str,
    res: DiagnosisResult,
    *,
    source: str = "",
    model: str = "",
    truth: dict | None = None,
    config: dict | None = None,
    base_spec: str | None = None,
) -> dict:
    """Write report.json, report.md, the figures and, when effects were added and
    ``base_spec`` (the model's ``jaxcal.models.load`` spec) is given, the extended
    model ``extended_model.json`` into ``out_dir``.

    Returns:
        The report dict (as written to report.json, with the figure paths).
    """
    os.makedirs(out_dir, exist_ok=True)
    rep = report_dict(res, source=source, model=model, truth=truth, config=config)
    rep["extended_model"] = None
    if res.members:
        names = [a.name for a in added_parameters(res)]
        rep["extended_model"] = {"parameters": list(res.declared) + names, "file": None}
        if base_spec:
            write_extended(out_dir, res, base_spec)
            rep["extended_model"]["file"] = "extended_model.json"
    figures = {
        "residuals": _stacked_residuals(os.path.join(out_dir, "residuals.png"), res),
        "signature": _explained(os.path.join(out_dir, "signature.png"), res),
        "theta": _theta(os.path.join(out_dir, "theta.png"), res),
        "units": _unit_map(os.path.join(out_dir, "units.png"), res),
    }
    figures = {k: v for k, v in figures.items() if v is not None}
    rep["figures"] = {k: os.path.basename(v) for k, v in figures.items()}
    write_text(os.path.join(out_dir, "report.json"), json.dumps(rep, indent=1) + "\n")
    write_text(os.path.join(out_dir, "report.md"), render_markdown(rep))
    return rep
