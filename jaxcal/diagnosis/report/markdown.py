"""The human-readable page of a diagnosis (report.md).

Pure text from the report dict of :mod:`jaxcal.diagnosis.report.write` (no plotting).
:func:`render_markdown` assembles the page from one function per section; numbers and
one-line summaries are worded by :mod:`jaxcal.diagnosis.report.formatting` (re-exported
here), so a console line (:mod:`jaxcal.cli.diagnose`, experiments/loop_cmapss.py) reads
the same. Each added effect gets its per-unit table, carriers listed and the rest
counted (:func:`_unit_table`).
"""

from __future__ import annotations

import math

import numpy as np

from jaxcal.diagnosis.report.formatting import (  # noqa: F401 (re-exported: the wording)
    dropped_rows_line,
    effect_line,
    fmt_p,
    fmt_std,
    verdict_line,
)
from jaxcal.diagnosis.report.formatting import fmt_value as _fmt  # short: many cells

MAX_UNIT_ROWS = 100  # carriers listed in report.md (all are in report.json)


def _unit_table(e: dict) -> list[str]:
    units = e["units"]
    carriers = [u for u in units if u["carries"]]
    rest = [u for u in units if not u["carries"]]
    lines = [
        f"### {e['name']} per unit",
        "",
        f"Carried by **{len(carriers)} of {len(units)} units** ({e['unit_test']}). "
        f"Onset: {e['onset_rule']}. Mean size: carriers "
        f"{_fmt(e.get('size_carriers'))}, others {_fmt(e.get('size_others'))} "
        f"{e['unit']}.",
        "",
    ]
    if carriers:
        shown = sorted(
            carriers, key=lambda u: -abs(u["size"] / (u["size_std"] or math.inf))
        )[:MAX_UNIT_ROWS]
        shown.sort(key=lambda u: u["unit"])
        lines += [
            "| unit | size | std | size / std | onset | onset 95 % interval |",
            "|---|---|---|---|---|---|",
        ]
        for u in shown:
            z = u["size"] / u["size_std"] if u["size_std"] else None
            ci = u.get("onset_ci")
            ci = f"{_fmt(ci[0])} – {_fmt(ci[1])}" if ci else "–"
            lines.append(
                f"| {u['unit']} | {_fmt(u['size'])} | {fmt_std(u['size_std'])} | "
                f"{_fmt(z, 3)} | {_fmt(u['onset'])} | {ci} |"
            )
        if len(carriers) > len(shown):
            lines.append(
                f"\n{len(carriers) - len(shown)} more carriers (smaller |z|) in "
                "report.json."
            )
        lines.append("")
    if rest:
        sizes = np.array([u["size"] for u in rest if u["size"] is not None])
        sizes = sizes[np.isfinite(sizes)]
        spread = (
            f"; their sizes: median {np.median(sizes):.4g}, range "
            f"[{sizes.min():.4g}, {sizes.max():.4g}] {e['unit']}"
            if sizes.size
            else ""
        )
        lines += [f"{len(rest)} units do not carry it{spread}.", ""]
    return lines


def _noise_lines(noise: dict, units: dict) -> list[str]:
    """The noise model: level, AR colour and whiteness after prewhitening."""
    lines = [
        "## Noise model",
        "",
        "Every likelihood, test and standard error is computed on the residual "
        "prewhitened by an AR(p) model per output (order by BIC, fitted to the "
        "declared-only fit's residual and corrected for what that fit absorbs); "
        "where AR(p) does not whiten it (Ljung–Box p < 0.01), the output's variance is "
        "inflated by its long-run variance ratio (HAC).",
        "",
        "| output | std | AR coefficients | HAC inflation | Ljung–Box p "
        "(prewhitened) |",
        "|---|---|---|---|---|",
    ]
    for s, std in noise["std"].items():
        ar = ", ".join(f"{v:.2f}" for v in noise["ar"][s]) or "white"
        lines.append(
            f"| {s} [{units.get(s, '-')}] | {_fmt(std)} | {ar} | "
            f"{noise['inflation'][s]:.2f} | {fmt_p(noise['whiteness_p'][s])} |"
        )
    return lines + [""]


def _header_lines(rep: dict) -> list[str]:
    """Title, the data in one paragraph, the verdict; then the noise model, the
    dropped rows and the excluded outputs when the report has them."""
    d = rep["data"]
    lines = [
        f"# Diagnosis: {rep['source'] or 'record'}",
        "",
        f"Model `{rep['model']}`, declared (calibrated): "
        f"{', '.join(f'`{n}`' for n in rep['declared'])}. {d['rows']} rows, "
        f"{d['units']} units, {len(d['sensors'])} outputs in the residual; noise std "
        f"{d['noise_source']}; {d['knots_per_unit']} spline functions per unit and "
        "declared parameter." + "".join(f" {n}." for n in d["notes"]),
        "",
        verdict_line(rep),
        "",
    ]
    if d.get("noise"):
        lines += _noise_lines(d["noise"], d.get("units_of") or {})
    dropped = d.get("dropped") or {}
    if dropped.get("rows") or dropped.get("columns"):
        lines += [dropped_rows_line(dropped) + ".", ""]
    if d["excluded"]:
        lines += [
            "Not in the residual: "
            + "; ".join(f"{k} ({v})" for k, v in d["excluded"].items())
            + ".",
            "",
        ]
    return lines


def _plausibility_lines(rep: dict) -> list[str]:
    """The plausibility flags (or the sentence that there are none), then the
    fallback note when the loop fell back."""
    flags = rep.get("flags") or []
    lines = ["## Plausibility", ""]
    if flags:
        lines += [f"- **{f['flag']}** ({f['subject']}): {f['detail']}." for f in flags]
    else:
        lines.append(
            "No flag: no effect outside the model's bounds, no parameter better than "
            "new, no loss constant from the first cycle, no declared parameter "
            "moved against its direction of wear, no sensor worse after the extension."
        )
    lines.append("")
    if rep.get("fallback_note"):
        lines += [f"Fallback: {rep['fallback_note']}.", ""]
    return lines


def _identified_lines(rep: dict) -> list[str]:
    """The identified effects' table, each effect's per-unit table after it, and the
    confounded set."""
    lines = []
    if rep["identified"]:
        lines += [
            "## Identified effect",
            "",
            "Sizes and standard errors from the final fit. A per-unit parameter's "
            "size is its change over each unit's record (mean over units), its "
            "departure from nominal at the first and last cycle beside it; carriers "
            "and the others apart below.",
            "",
            "| effect | size | std | unit | at first / last cycle | carriers |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {e['name']} | {_fmt(e['size'])} | {fmt_std(e['std'])} | {e['unit']} "
            f"| {_fmt(e.get('start_value'))} / {_fmt(e.get('end_value'))} "
            f"| {e.get('carriers', '–')} of {rep['data']['units']} |"
            for e in rep["identified"]
        ]
        lines.append("")
        for e in rep["identified"]:
            lines += _unit_table(e)
    if rep["confounded"]:
        lines += [
            f"Confounded (signatures nearly collinear after projecting out the "
            f"declared parameters, BIC within the margin): "
            f"{', '.join(rep['confounded'])}. The first stands in for the set.",
            "",
        ]
    return lines


def _discrepancy_lines(rep: dict) -> list[str]:
    """The discrepancy delta(w) per sensor, with what it depends on (none: no lines)."""
    if not rep["discrepancy"]:
        return []
    units = rep["data"].get("units_of") or {}
    lines = [
        "## Discrepancy delta(w) (not explained by the library)",
        "",
        "Shares of the cross-validated gain: *alone* = an offset only "
        "(constant), or what delta on that input alone adds to the offset; "
        "*unique* = lost when the input is dropped from the full delta.",
        "",
        "| sensor | std of delta | mean of delta | CV gain / threshold | "
        "alone | unique |",
        "|---|---|---|---|---|---|",
    ]
    for s in rep["discrepancy"]:
        dep, uni = (
            ", ".join(
                f"{k} {v:.2f}" for k, v in sorted(s[key].items(), key=lambda kv: -kv[1])
            )
            for key in ("dependence", "unique")
        )
        lines.append(
            f"| {s['sensor']} [{units.get(s['sensor'], '-')}] | "
            f"{_fmt(s['amplitude_units'])} | "
            f"{_fmt(s['mean_units'])} | {s['cv_gain']:.0f} / "
            f"{s['threshold']:.0f} | {dep} | {uni} |"
        )
    lines.append("")
    return lines


def _ranking_lines(rep: dict) -> list[str]:
    """The first ten candidates of the ranking and the absorbed ones."""
    lines = [
        "## Ranking (declared-only residual)",
        "",
        f"{rep['num_tests']} tests; delta BIC > 0 favours the candidate over the "
        "declared-only model; LR = SSR_0 - SSR (chi2 with df).",
        "",
        "| # | candidate | df | LR | log10 p | delta BIC | size (own refit) | refit "
        "| detectability |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for i, e in enumerate(rep["ranking"][:10]):
        size = ", ".join(_fmt(s) for s in e["screen_sizes"])
        lines.append(
            f"| {i + 1} | {e['name']} | {e['df']} | {_fmt(e['lr_stat'], 6)} | "
            f"{_fmt(e['log10_p'], 4)} | {_fmt(e['delta_bic'], 6)} | {size} | "
            f"{'yes' if e['refit'] else 'linear'} | {e['detectability']:.2f} |"
        )
    if rep["absorbed"]:
        lines += [
            "",
            "Absorbed by the declared parameters (undetectable in the residual): "
            + ", ".join(rep["absorbed"])
            + ".",
        ]
    return lines


def _before_after_lines(rep: dict) -> list[str]:
    """What was added and the errors before and after, per output."""
    d, b, a = rep["data"], rep["before"], rep["after"]
    units = d.get("units_of") or {}
    lines = [
        "",
        "## Before / after",
        "",
        f"Added: {', '.join(rep['added']) or 'nothing'}. Mean tracking RMSE "
        f"{b['mean_tracking_rmse_norm']:.3f} -> {a['mean_tracking_rmse_norm']:.3f} "
        f"noise std; white outputs after prewhitening (Ljung–Box p > 0.01) "
        f"{b['whiteness']:.2f} -> {a['whiteness']:.2f}; BIC {b['bic']:.1f} -> "
        f"{a['bic']:.1f}.",
        "",
        "| output | unit | RMSE before | after | before / std | after / std "
        "| LB p before (prewhitened) | after |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in d["sensors"]:
        lines.append(
            f"| {s} | {units.get(s, '-')} | {_fmt(b['tracking_rmse'][s])} | "
            f"{_fmt(a['tracking_rmse'][s])} | "
            f"{b['tracking_rmse_norm'][s]:.3f} | {a['tracking_rmse_norm'][s]:.3f} | "
            f"{fmt_p(b['whiteness_p'][s])} | {fmt_p(a['whiteness_p'][s])} |"
        )
    return lines


def _closing_lines(rep: dict) -> list[str]:
    """The extended model, theta errors against a known truth, the truth itself and
    the figures: each only when the report has it."""
    lines = []
    ext = rep.get("extended_model")
    if ext:
        where = (
            f"`{ext['file']}` (`model={ext['file']}` on any command line)"
            if ext.get("file")
            else "`result.extended_model` (Python)"
        )
        lines += [
            "",
            "## The extended model",
            "",
            f"Parameters {', '.join(f'`{n}`' for n in ext['parameters'])}: the "
            f"declared ones and each added effect, tracked in real time by any "
            f"method. In {where}.",
        ]
    b, a = rep["before"], rep["after"]
    if b["theta_rmse"]:
        lines += ["", "| theta RMSE vs truth | before | after |", "|---|---|---|"]
        for k in a["theta_rmse"]:
            lines.append(
                f"| {k} | {_fmt(b['theta_rmse'].get(k))} | {_fmt(a['theta_rmse'][k])} |"
            )
    if rep.get("truth"):
        lines += [
            "",
            "Truth: " + ", ".join(f"{k}={_fmt(v)}" for k, v in rep["truth"].items()),
        ]
    if rep.get("figures"):
        lines += ["", "## Figures", ""]
        lines += [f"![{k}]({v})" for k, v in rep["figures"].items()]
    return lines


def render_markdown(rep: dict) -> str:
    """The human-readable page of a report dict, its sections in reading order."""
    lines = [
        *_header_lines(rep),
        *_plausibility_lines(rep),
        *_identified_lines(rep),
        *_discrepancy_lines(rep),
        *_ranking_lines(rep),
        *_before_after_lines(rep),
        *_closing_lines(rep),
    ]
    return "\n".join(lines) + "\n"
