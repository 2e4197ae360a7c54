"""The theta std under model error: flag it, or widen it? (issue 26, item 5)

    python experiments/misfit_battery.py [data=data/battery] [out=results/std_coverage]

The battery example (``examples/battery``: an equivalent-circuit model tracking
PyBaMM SPMe cells, 18 mV of model error) through ``jaxcal.calibrate`` with the
example's settings: the UKF with the noise given (the example's 0.02 V) and
estimated, least squares with it given. Per case:

* the 90 % coverage of the reported std on the test cells 3-4 and on every cell
  (rows from cycle 1 on, the example's scoring rule);
* the share of rows ``result.misfit`` marks, and each cell's largest long-run
  variance ratio of the screening's one-step innovations
  (:func:`jaxcal.calibrators.uncertainty.misfit_check.misfit_rows`);
* the alternative measured and rejected: the std widened by the square root of that
  ratio (the effective-sample-size argument), and the factor each cell's std would
  need (the 90 % quantile of ``|error| / std`` over 1.6449).

Writes ``<out>/misfit_battery.json`` and ``<out>/misfit_battery.md``; the data are
made by ``examples/battery/make_data.py`` when missing (PyBaMM, ``make battery``'s
extra).
"""

from __future__ import annotations

import json
import os
import sys
import warnings

import numpy as np
import pandas as pd

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, os.path.join(ROOT, "examples", "battery"))
Z90 = 1.6448536269514722
TEST_CELLS = (3, 4)
CASES = (("ukf", "given"), ("ukf", "estimated"), ("ls", "given"))


def _case(frame: pd.DataFrame, method: str, noise: str) -> dict:
    from model import MODEL
    from peers import THETA, UKF

    import jaxcal
    from jaxcal.calibrators.front import screen_memo
    from jaxcal.calibrators.uncertainty.misfit_check import misfit_rows

    if method == "ukf":
        options = {k: UKF[k] for k in ("q", "prior_std", "state_std", "state_q")}
    else:
        options = {"window": 360, "num_iters": 3}
    options["misfit"] = "keep"  # the std the flag withholds by default: measured
    given = {"voltage": UKF["noise"]} if noise == "given" else None
    data = frame[["unit", "time", "current", "dt", "voltage"]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        res = jaxcal.calibrate(MODEL, data, method, theta=THETA, noise=given,
                               progress=False, **options)  # fmt: skip
    kept = screen_memo.latest()  # the screening this call used: its innovations
    _, ratio = misfit_rows(res.unit, res.time, kept.z, kept.used)
    widen = np.sqrt(np.maximum(np.nan_to_num(ratio, nan=1.0).max(axis=1), 1.0))
    err = np.abs(res.theta - frame[["R0_true", "Q_true"]].to_numpy())
    scored = res.valid & (frame.cycle.to_numpy() >= 1)
    doc = {"noise_std": [float(v) for v in res.problem.noise_std]}
    for name, rows in (("test cells 3-4", np.isin(res.unit, TEST_CELLS)),
                       ("all cells", np.ones_like(scored))):  # fmt: skip
        keep = scored & rows
        doc[name] = {
            "coverage": _share(err[keep] <= Z90 * res.theta_std[keep]),
            "coverage_widened": _share(
                err[keep] <= Z90 * res.theta_std[keep] * widen[keep, None]
            ),
            "misfit_share": float(res.misfit[keep].mean()),
        }
    doc["cells"] = {
        int(u): {
            "ratio": float(np.nanmax(ratio[res.unit == u])),
            "factor_needed": _rounded(
                np.quantile(err[m] / res.theta_std[m], 0.9, axis=0) / Z90
            ),
        }
        for u in np.unique(res.unit)
        for m in [scored & (res.unit == u)]
    }
    return doc


def _share(values) -> list[float]:
    return _rounded(np.mean(values, axis=0))


def _rounded(values) -> list[float]:
    return [round(float(v), 3) for v in values]


def render(doc: dict) -> str:
    lines = [
        "# The theta std under model error: the battery example",
        "",
        "`python experiments/misfit_battery.py` (issue 26, item 5): 90 % coverage of",
        "the reported std (R0 / Q, rows from cycle 1 on), the share of rows",
        "`result.misfit` marks, and the coverage had the std been widened by the",
        "square root of the cell's long-run variance ratio of the screening's one-step",
        "innovations (the alternative measured and rejected).",
        "",
        "| method | noise | cells | coverage | flagged | widened: coverage |",
        "|---|---|---|---|---|---|",
    ]
    for key, case in doc.items():
        method, noise = key.split("/")
        for cells in ("test cells 3-4", "all cells"):
            c = case[cells]
            lines.append(
                f"| {method} | {noise} | {cells} | {_pair(c['coverage'])} | "
                f"{c['misfit_share']:.2f} | {_pair(c['coverage_widened'])} |"
            )
    lines += [
        "",
        "Per cell: the largest long-run variance ratio (white noise: 1; flagged above",
        "4) and the factor the std would need for 90 % (R0 / Q).",
        "",
        "| method | noise | cell | ratio | factor needed |",
        "|---|---|---|---|---|",
    ]
    for key, case in doc.items():
        method, noise = key.split("/")
        for cell, c in case["cells"].items():
            lines.append(
                f"| {method} | {noise} | {cell} | {c['ratio']:.1f} | "
                f"{_pair(c['factor_needed'], '.2f')} |"
            )
    return "\n".join(lines) + "\n"


def _pair(values, fmt=".3f") -> str:
    return " / ".join(format(v, fmt) for v in values)


def main(argv: list[str]) -> None:
    opts = {"data": "data/battery", "out": "results/std_coverage"}
    opts.update(a.split("=", 1) for a in argv)
    import make_data

    from jaxcal.runs.atomic import write_atomic

    path = make_data.main([f"out={opts['data']}"])
    frame = pd.read_csv(path)
    doc = {}
    for method, noise in CASES:
        print(f"battery {method} {noise}", file=sys.stderr, flush=True)
        doc[f"{method}/{noise}"] = _case(frame, method, noise)
    print(json.dumps(doc, indent=1))
    os.makedirs(opts["out"], exist_ok=True)
    base = os.path.join(opts["out"], "misfit_battery")
    write_atomic(f"{base}.json", json.dumps(doc, indent=1) + "\n")
    write_atomic(f"{base}.md", render(doc))


if __name__ == "__main__":
    main(sys.argv[1:])
