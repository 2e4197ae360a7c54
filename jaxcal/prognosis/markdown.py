"""The text of a prognosis's ``report.md`` (:mod:`jaxcal.prognosis.report` writes it).

The page says what was done (training units, trend, deciding boundaries, samples and
coverage), the failure boundaries (value, spread, tightness, whether each decides),
the score against the truth when there is one, the held-out noise check, a per-unit
table linked to each unit's figure (every unit of a small fleet; else the first
:data:`TABLE_FIRST` and the :data:`TABLE_WORST` worst), the fleet figure, the notes
and the stage timings. It reads only the report dict, so ``report.json`` re-renders it.
"""

from __future__ import annotations

import json

TABLE_FIRST = 20  # units listed first in report.md ...
TABLE_WORST = 10  # ... then the worst (largest error, or shortest RUL without truth)
UNITS_DIR = "units"  # the per-unit figures' folder, relative to the report


def _f(value, fmt: str = ".1f") -> str:
    return "–" if value is None else format(value, fmt)


def _unit_table(rep: dict) -> list[str]:
    """The per-unit table: every unit of a small fleet, else the first
    :data:`TABLE_FIRST` and the :data:`TABLE_WORST` worst (largest error with the
    truth, shortest RUL without: the most urgent)."""
    rows, has_truth = rep["units"], "score" in rep
    picked = list(range(len(rows)))
    if len(rows) > TABLE_FIRST + TABLE_WORST:
        key = (
            (lambda i: -abs(rows[i]["error"]))
            if has_truth
            else (lambda i: rows[i]["rul"])
        )
        worst = sorted(range(TABLE_FIRST, len(rows)), key=key)[:TABLE_WORST]
        picked = list(range(TABLE_FIRST)) + sorted(worst)
    head = "| unit | age | RUL | interval |" + (" true | error |" if has_truth else "")
    lines = [
        head + " driver (share) | censored |",
        "|---" * (head.count("|") + 1) + "|",
    ]
    for i in picked:
        r = rows[i]
        link = rep["figures"]["units"].get(r["unit"])  # drawn units only
        cells = [
            f"[{r['unit']}]({link})" if link else r["unit"],
            _f(r["now"], ".0f"),
            _f(r["rul"]),
            f"[{_f(r['low'])}, {_f(r['high'])}]",
        ]
        if has_truth:
            cells += [_f(r["truth"], ".0f"), _f(r["error"], "+.1f")]
        cells += [
            f"{r['driver']} ({_f(r['driver_share'], '.0%')})",
            _f(r["censored"], ".0%"),
        ]
        if i > TABLE_FIRST and i - 1 not in picked:  # a gap before the worst
            lines.append("| … |" + " |" * (len(cells) - 1))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def render_markdown(rep: dict) -> str:
    """The text of ``report.md`` from the report dict (figure paths included)."""
    m = rep["model"]
    decide = [n for n, b in m["boundary"].items() if b["decides"]]
    lines = [
        "# Remaining useful life",
        "",
        f"{rep['training_units']} run-to-failure training units taught the fleet's "
        f"degradation of {', '.join(m['parameters'])} ({m['trend']}; training lives "
        f"{m['training_life']['min']:.0f}–{m['training_life']['max']:.0f}, mean "
        f"{m['training_life']['mean']:.0f}). Each of the {rep['test_units']} test "
        "units' calibrated trajectory updated that prior; its RUL is the median of "
        f"{rep['samples']} sampled first crossings of a deciding boundary "
        f"({', '.join(decide)}), with the central {rep['coverage']:.0%} interval.",
        "",
        (f"Sources: `{json.dumps(rep['sources'])}`. " if rep["sources"] else "")
        + "Predictions: [rul.csv](rul.csv); everything: [report.json](report.json).",
        "",
        "## Failure boundaries",
        "",
        "| parameter | value | spread | tightness | decides | declared |",
        "|---|---|---|---|---|---|",
    ]
    for name, b in m["boundary"].items():
        yes = ["yes" if b[k] else "no" for k in ("decides", "declared")]
        cells = [
            name,
            f"{b['value']:.5g}",
            f"{b['std']:.3g}",
            _f(b["tightness"], ".2f"),
        ]
        lines.append("| " + " | ".join([*cells, *yes]) + " |")
    if "score" in rep:
        s = rep["score"]
        lines += [
            "",
            "## Score against the truth",
            "",
            "| units | RMSE | mean error | PHM08 score | coverage | mean width "
            "| CRPS |",
            "|---|---|---|---|---|---|---|",
            f"| {s['units']} | {s['rmse']:.2f} | {s['mean_error']:+.2f} | "
            f"{s['phm08_score']:.1f} | {s['coverage']:.3f} "
            f"(nominal {rep['coverage']:.2f}) | {s['mean_width']:.1f} | "
            f"{_f(s.get('crps'))} |",
        ]
    check = rep.get("noise_check") or {}
    if check.get("scales"):
        lines += [
            "",
            "## Trend and noise scale (held-out training units)",
            "",
            f"{check['cases']} cases: training units cut at random ages, predicted by "
            "the model learned on the other folds. Chosen (bold): the lowest CRPS "
            "among the honest pairs, whose coverage is within two binomial standard "
            "errors of the nominal one.",
            "",
            "| trend | noise scale | CRPS | coverage | RMSE | honest |",
            "|---|---|---|---|---|---|",
        ]
        for i, trend in enumerate(check["trends"]):
            for j, scale in enumerate(check["scales"]):
                chosen = trend == check["trend"] and scale == check["noise_scale"]
                cells = [
                    trend, _f(scale, ".3g"), _f(check["crps"][i][j]),
                    _f(check["coverage"][i][j], ".3f"), _f(check["rmse"][i][j]),
                    "–" if "honest" not in check
                    else ("yes" if check["honest"][i][j] else "no"),
                ]  # fmt: skip
                if chosen:
                    cells = [f"**{c}**" for c in cells]
                lines.append("| " + " | ".join(cells) + " |")
    elif check:
        lines += [
            "",
            f"Trend {check['trend']} and noise scale {check['noise_scale']:g} "
            "given (no held-out check).",
        ]
    lines += [
        "",
        "## Units",
        "",
        *_unit_table(rep),
        "",
        "## Figures",
        "",
        f"![predicted RUL]({rep['figures']['fleet']})",
        "",
        f"{len(rep['figures']['units'])} unit figure(s) in [{UNITS_DIR}/]({UNITS_DIR}/)"
        " (linked above).",
    ]
    if rep["notes"]:
        lines += ["", "## Notes", "", *(f"- {n}" for n in rep["notes"])]
    timings = ", ".join(f"{k} {_f(v)} s" for k, v in rep["timings"].items())
    lines += ["", f"Timings: {timings}."]
    return "\n".join(lines) + "\n"
