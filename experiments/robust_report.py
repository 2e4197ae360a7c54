"""Summary, figure and page of the robust study (loop_robust.py), from its records.

``summary.json`` has exactly the issue's keys: ``false_alarm_rate``,
``identification`` (``{kind: {"2x", "5x", "10x"}}``), ``unit_hit_rate`` (carriers
flagged, sizes >= 5x), ``onset_error`` (median over the step kinds of
``|onset - truth| / record length``) and ``per_model`` (the same four per model).
``study.json`` keeps the counts behind every rate.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os

import numpy as np

from jaxcal.diagnosis.report.write import json_safe
from jaxcal.runs.atomic import write_atomic

STEP_KINDS = ("sensor_step", "parameter_step")
LEVERS = {  # lever -> what was switched off (levers/<name>/ beside the study)
    "white_noise": "the noise model (white noise, noise_order=0)",
    "fleet_only": "per-unit forms and steps (forms=fleet)",
    "no_steps": "the step kinds (without=sensor_step,parameter_step)",
}


def _rate(values):
    return float(np.mean(values)) if len(values) else None


def _mult_key(m: float) -> str:
    return f"{m:g}x"


def four(rows: list[dict], multiples) -> tuple[dict, dict]:
    """The issue's four entries over ``rows`` and their counts."""
    clean = [r for r in rows if r["kind"] == "none"]
    eff = [r for r in rows if r["kind"] != "none"]
    ident, strict, counts = {}, {}, {}
    for kind in sorted({r["kind"] for r in eff}):
        ident[kind], strict[kind], counts[kind] = {}, {}, {}
        for m in multiples:
            sel = [r for r in eff if r["kind"] == kind and r["multiple"] == m]
            ident[kind][_mult_key(m)] = _rate([r.get("named", r["first"]) for r in sel])
            strict[kind][_mult_key(m)] = _rate([r["first"] for r in sel])
            counts[kind][_mult_key(m)] = len(sel)
    hits = [u in r["flagged"] for r in eff if r["multiple"] >= 5.0
            for u in r["carriers"]]  # fmt: skip
    # non-carriers flagged, in records where the truth was named (its stand-in)
    false_flags = [u in r["flagged"] for r in eff if r.get("named")
                   for u in r["units"] if u not in r["carriers"]]  # fmt: skip
    onset = [e for r in eff if r["kind"] in STEP_KINDS for e in r["onset_error"]]
    out = {
        "false_alarm_rate": _rate([r["verdict"] != "none" for r in clean]),
        "identification": ident,
        "unit_hit_rate": _rate(hits),
        "onset_error": float(np.median(onset)) if onset else None,
    }
    n = {"clean": len(clean), "identification": counts, "carriers_5x": len(hits),
         "errors": sum(r["verdict"] == "error" for r in rows),
         "unit_false_flag_rate": _rate(false_flags), "non_carriers": len(false_flags),
         "onsets": len(onset), "identification_strict": strict}  # fmt: skip
    return out, n


def summarize(rows: list[dict], multiples) -> tuple[dict, dict]:
    """``(summary.json, counts)`` over all models and per model."""
    summary, counts = four(rows, multiples)
    summary["per_model"], counts["per_model"] = {}, {}
    for model in sorted({r["model"] for r in rows}):
        mine = [r for r in rows if r["model"] == model]
        summary["per_model"][model], counts["per_model"][model] = four(mine, multiples)
    return summary, counts


def plot(summary: dict, multiples) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = list(summary["per_model"])
    fig, axes = plt.subplots(1, len(models), figsize=(4.2 * len(models), 4.0),
                             sharey=True, squeeze=False)  # fmt: skip
    for ax, model in zip(axes[0], models, strict=True):
        per = summary["per_model"][model]
        for kind, rates in per["identification"].items():
            ys = [rates[_mult_key(m)] for m in multiples]
            ax.plot(multiples, [np.nan if y is None else y for y in ys], "o-",
                    label=kind)  # fmt: skip
        fa = per["false_alarm_rate"]
        if fa is not None:
            ax.axhline(fa, color="k", ls="--", label=f"false alarm {fa:.2f}")
        ax.axhline(0.9, color="0.6", lw=0.8)
        ax.set_xscale("log")
        ax.set_xticks(list(multiples), [_mult_key(m) for m in multiples])
        ax.set_xlabel("effect size / the record's detectability size")
        ax.set_title(f"{model}: identification", fontsize=10)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def _fmt(v):
    return "–" if v is None else f"{v:.2f}"


def _table(summary: dict, counts: dict, multiples) -> list[str]:
    head = " | ".join(_mult_key(m) for m in multiples)
    lines = [
        f"| kind | named {head} | strict {head} | n per cell |",
        "|---|" + "---|" * (2 * len(multiples) + 1),
    ]
    for kind, rates in summary["identification"].items():
        ns = sorted(set(counts["identification"][kind].values()))
        strict = counts["identification_strict"][kind]
        lines.append(
            f"| {kind} | "
            + " | ".join(_fmt(rates[_mult_key(m)]) for m in multiples)
            + " | "
            + " | ".join(_fmt(strict[_mult_key(m)]) for m in multiples)
            + f" | {'/'.join(str(n) for n in ns)} |"
        )
    return lines


def _before() -> list[str]:
    """The study before issue 24 (turbofan only, its own size scale), for reference."""
    path = "results/loop/robust/before_issue24/study.json"
    if not os.path.exists(path):
        return []
    with open(path) as f:
        old = json.load(f)["summary"]
    lines = [
        "## Before (the diagnosis of before issue 24, turbofan only)",
        "",
        "From `results/loop/robust/before_issue24/` (its sizes were multiples of one "
        "detectability size per kind on a nominal white-noise record, so a coloured "
        "record with few carriers held far less signal at the same multiple):",
        "",
        "| kind | 2x | 5x | 10x |",
        "|---|---|---|---|",
    ]
    for kind, per in old["kinds"].items():
        lines.append(f"| {kind} | " + " | ".join(
            _fmt(per.get(k, {}).get("identified")) for k in ("2.0", "5.0", "10.0")
        ) + " |")  # fmt: skip
    lines += [
        "",
        f"False alarms {_fmt(old['false_alarm'])} (n = {old['false_alarm_n']}); unit "
        f"hit rate (>= 2x) {_fmt(old['unit_hit'])}; no step kinds, no onset error.",
        "",
    ]
    return lines


GOALS = {  # the bar: summary key -> (test, text)
    "false_alarm_rate": (lambda v: v <= 0.05, "<= 0.05"),
    "ident_5x": (lambda v: v >= 0.9, ">= 0.9"),
    "ident_2x": (lambda v: v >= 0.6, ">= 0.6"),
    "unit_hit_rate": (lambda v: v >= 0.9, ">= 0.9"),
    "onset_error": (lambda v: v <= 0.10, "<= 0.10"),
}


def _goal_cells(s: dict) -> list[str]:
    """Each goal's number for one summary (the lowest rate over kinds for the
    identification), marked met or not (``–``: nothing to measure)."""
    lowest = {}
    for m in ("5x", "2x"):
        rates = [v[m] for v in s["identification"].values() if v.get(m) is not None]
        lowest[f"ident_{m}"] = min(rates) if rates else None
    cells = []
    for key, (ok, _) in GOALS.items():
        v = lowest[key] if key in lowest else s.get(key)
        cells.append(
            "–" if v is None else f"{_fmt(v)} {'met' if ok(v) else '**not met**'}"
        )
    return cells


def _goals(summary: dict, out: str) -> list[str]:
    """The issue's goals, overall and per model (the lowest kind for identification)."""
    head = "| | " + " | ".join(
        ["false alarms", "identification 5x (lowest kind)",
         "identification 2x (lowest kind)", "unit hit rate", "onset error"]
    ) + " |"  # fmt: skip
    lines = [
        "## Against the goals",
        "",
        head,
        "|---|" + "---|" * len(GOALS),
        "| goal | " + " | ".join(text for _, text in GOALS.values()) + " |",
        "| all models | " + " | ".join(_goal_cells(summary)) + " |",
    ]
    for model, per in summary["per_model"].items():
        lines.append(f"| {model} | " + " | ".join(_goal_cells(per)) + " |")
    before_after = "levers/before_after/README.md"
    if not os.path.exists(os.path.join(out, before_after)):
        return [*lines, ""]
    lines += ["", f"Before and after issue 24 on the same records: [{before_after}]"
              f"({before_after}).", ""]  # fmt: skip
    return lines


def _lever_row(label: str, s: dict) -> str:
    ident5 = [v["5x"] for v in s["identification"].values() if v.get("5x")
              is not None]  # fmt: skip
    return (
        f"| {label} | {_fmt(s['false_alarm_rate'])} | "
        f"{_fmt(min(ident5) if ident5 else None)} | "
        f"{_fmt(s['unit_hit_rate'])} | {_fmt(s['onset_error'])} |"
    )


def _levers(out: str, rows: list[dict], multiples) -> list[str]:
    """One row per lever run found under ``<out>/levers/``, beside the full
    diagnosis on the same records (the main run's rows of the lever's seeds)."""
    lines = []
    for name, what in LEVERS.items():
        path = os.path.join(out, "levers", name, "study.json")
        if not os.path.exists(path):
            continue
        with open(path) as f:
            lever = json.load(f)
        cfg = lever["config"]
        same = [
            r for r in rows if r["model"] in cfg["models"]
            and r["seed"] < cfg["clean" if r["kind"] == "none" else "seeds"]
        ]  # fmt: skip
        lines += [
            _lever_row(f"without {what}", lever["summary"]),
            _lever_row("the full diagnosis, same records", four(same, multiples)[0]),
        ]
    if not lines:
        return []
    return [
        "## What each lever gives on its own",
        "",
        "The same records (same seeds) diagnosed with one lever switched off "
        "(`levers/<name>/`, a smaller run: its `study.json` has the command), each "
        "beside the full diagnosis on those records:",
        "",
        "| diagnosis | false alarms | lowest identification at 5x | unit hits | "
        "onset error |",
        "|---|---|---|---|---|",
        *lines,
        "",
    ]


def write(cfg, rows: list[dict], command: str, minutes: float | None) -> str:
    """Write summary.json, study.json, detection.png and README.md; the README."""
    summary, counts = summarize(rows, cfg.multiples)
    study_path = os.path.join(cfg.out, "study.json")
    if minutes is None and os.path.exists(study_path):
        with open(study_path) as f:
            old = json.load(f)
        command, minutes = old["command"], old["minutes"]
    elif os.path.exists(study_path):
        with open(study_path) as f:
            minutes += json.load(f).get("minutes") or 0.0
    write_atomic(os.path.join(cfg.out, "summary.json"),
                 json.dumps(json_safe(summary), indent=1) + "\n")  # fmt: skip
    payload = {"config": dataclasses.asdict(cfg), "command": command,
               "minutes": minutes, "counts": counts, "summary": summary}  # fmt: skip
    write_atomic(study_path, json.dumps(json_safe(payload), indent=1) + "\n")
    if summary["per_model"]:
        write_atomic(os.path.join(cfg.out, "detection.png"),
                     plot(summary, cfg.multiples))  # fmt: skip
    lines = [
        "# Closing the loop on data that look measured: three models",
        "",
        f"Command: `{command}` ({minutes or 0:.0f} min of wall time on this shared "
        "2-core machine). Records drawn by `experiments/robust_scenario.py`; sizes "
        "are multiples of each record's own detectability size "
        "(`experiments/loop_robust.py` says how it is computed); noise level and "
        "colour estimated by the diagnosis. *Named*: the diagnosis adds the true "
        "effect, or reports it in a confounded set with the effect it adds (two "
        "effects the data cannot tell apart, e.g. a bias and a gain of an output "
        "whose level barely changes); *strict*: it adds exactly the truth.",
        "",
        "![identification per model](detection.png)",
        "",
        f"**All models**: false alarms {_fmt(summary['false_alarm_rate'])} "
        f"(n = {counts['clean']}), unit hit rate (>= 5x) "
        f"{_fmt(summary['unit_hit_rate'])} (n = {counts['carriers_5x']} carriers), "
        f"onset error {_fmt(summary['onset_error'])} of the record (median, n = "
        f"{counts['onsets']}); non-carrier units flagged where the truth was named "
        f"{_fmt(counts['unit_false_flag_rate'])} (n = {counts['non_carriers']}); "
        f"diagnoses that raised an error (counted as misses): {counts['errors']}.",
        "",
        *_table(summary, counts, cfg.multiples),
        "",
        *_goals(summary, cfg.out),
    ]
    for model, per in summary["per_model"].items():
        c = counts["per_model"][model]
        lines += [
            f"## {model}",
            "",
            f"False alarms {_fmt(per['false_alarm_rate'])} (n = {c['clean']}); unit "
            f"hit rate {_fmt(per['unit_hit_rate'])} (n = {c['carriers_5x']}); onset "
            f"error {_fmt(per['onset_error'])} (n = {c['onsets']}); non-carriers "
            f"flagged {_fmt(c['unit_false_flag_rate'])} (n = {c['non_carriers']}).",
            "",
            *_table(per, c, cfg.multiples),
            "",
        ]
    misses = [f"{r['model']}: {r['name']} {r['multiple']:g}x (seed {r['seed']}) -> "
              f"{' + '.join(r['added']) or r['verdict']}"
              for r in rows if r["kind"] != "none" and r["multiple"] >= 5.0
              and not r["first"]]  # fmt: skip
    alarms = [f"{r['model']} seed {r['seed']}: {r['verdict']} "
              f"{' + '.join(r['added'])}" for r in rows
              if r["kind"] == "none" and r["verdict"] != "none"]  # fmt: skip
    if alarms:
        lines += ["False alarms: " + "; ".join(alarms) + ".", ""]
    if misses:
        lines += ["Records at >= 5x where the added effect is not the truth: "
                  + "; ".join(misses) + ".", ""]  # fmt: skip
    lines += _levers(cfg.out, rows, cfg.multiples) + _before()
    text = "\n".join(lines) + "\n"
    write_atomic(os.path.join(cfg.out, "README.md"), text)
    return text
