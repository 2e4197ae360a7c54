"""How far below the UKF can a filter go under each effect? The UKF tuned on the test.

Issue 41, item 3 asks the policy for at most 0.5x the UKF's theta error under each
effect kind, AR(1)-coloured noise among them. The policy is a filter with a learned
gain: whatever it learns, it is one causal estimator among those a filter's settings
span. This script measures what the best of them reaches when its settings are chosen
*on the test units themselves* (an oracle, generous to the filter): the UKF over a
grid of theta's random walk ``q`` (its default 0.01 half-box widths a sample) and of
the declared noise scaled by ``r`` (1: the noise the data were made with), on the
policy study's test frames (``experiments/policy_robust.py``: the same cases, test
units, effects and seeds). Printed as JSON and written to
``results/policy_any_model/filter_bound.json`` (per case and effect the default
UKF's theta RMSE, the best of the grid, its settings and their ratio, the whole grid)
and ``filter_bound.md`` beside it, with the default policy's ratios of
``results/policy_robust/results.json`` for comparison.

    python experiments/filter_bound.py cases=heat_exchanger,motor,reactor
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import shlex
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from policy_any_model import _case, split_files  # noqa: E402
from policy_robust import EFFECTS, _score, with_effect  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Options:
    """The script's ``key=value`` options (module docstring)."""

    cases: str = "heat_exchanger,motor,reactor"
    effects: str = "clean,bias 3σ,AR(1) 0.8"
    qs: str = "0.0005,0.001,0.002,0.005,0.01,0.02"
    rs: str = "1,2,4"
    data: str = "data/policy_robust"
    out: str = "results/policy_any_model/filter_bound.json"
    seed: int = 0


def run_case(name: str, opts: Options) -> dict:
    import jaxcal

    spec, fleet, theta, noise = _case(name, opts.seed)
    model = jaxcal.models.load(spec)
    low, high = model.bounds
    index = [model.parameter_names.index(t) for t in theta]
    half = 0.5 * (high[index] - low[index])
    _, test = split_files(name, spec, fleet, opts.data)
    outputs = [o for o in model.output_names if o in noise]
    qs = [float(q) for q in opts.qs.split(",")]
    rs = [float(r) for r in opts.rs.split(",")]
    out = {}
    for label in opts.effects.split(","):
        kind, size = EFFECTS[label]
        # the policy study's frame: the same generator seed for every effect
        frame = with_effect(test, outputs, noise, kind, size, np.random.default_rng(7))
        grid = {}
        for q, r in itertools.product(qs, rs):
            scaled = {k: v * np.sqrt(r) for k, v in noise.items()}
            res = jaxcal.calibrate(
                spec, frame, method="ukf", theta=theta, noise=scaled, q=q,
                progress=False, misfit="keep",
            )  # fmt: skip
            grid[f"q={q:g},r={r:g}"] = _score(res, frame, theta, half)
        default = grid["q=0.01,r=1"]
        best = min(grid, key=grid.get)
        out[label] = {
            "ukf": default,
            "best": grid[best],
            "best_settings": best,
            "best_over_ukf": grid[best] / default,
            "grid": grid,
        }
        print(name, label, json.dumps({k: v for k, v in out[label].items()
                                       if k != "grid"}), flush=True)  # fmt: skip
    return out


def main(argv: list[str]) -> int:
    from jaxcal.settings import parse_overrides

    opts = parse_overrides(argv, Options())
    import jax

    jax.config.update("jax_enable_x64", True)  # entry point: the UKF wants float64
    tic = time.perf_counter()
    results = {name: run_case(name, opts) for name in opts.cases.split(",")}
    doc = {
        "options": dataclasses.asdict(opts),
        "seconds": time.perf_counter() - tic,
        "results": results,
    }
    os.makedirs(os.path.dirname(opts.out), exist_ok=True)
    with open(opts.out, "w") as f:
        json.dump(doc, f, indent=1)
    with open(os.path.splitext(opts.out)[0] + ".md", "w") as f:
        f.write(_page(doc, argv))
    return 0


def _policy_ratios(path: str = "results/policy_robust/results.json") -> dict:
    """``{case: {effect: policy / UKF}}`` of the policy study's default variant."""
    if not os.path.isfile(path):
        return {}
    with open(path) as f:
        results = json.load(f)["results"]
    out = {}
    for name, res in results.items():
        run = res["runs"].get("default")
        if run is not None:
            out[name] = {
                lab: run["theta_rmse"][lab] / res["ukf"][lab] for lab in res["ukf"]
            }
    return out


def _page(doc: dict, argv: list[str]) -> str:
    results = doc["results"]
    labels = list(next(iter(results.values())))
    policy = _policy_ratios()
    lines = [
        "# The best a filter of the UKF's kind reaches under each effect (issue 41)",
        "",
        f"`python experiments/filter_bound.py {shlex.join(argv)}` "
        f"({doc['seconds']:.0f} s, 2 cores). The UKF on the policy study's test units "
        "(`experiments/policy_robust.py`: the same frames, the effect on the first "
        "output from a third of each unit; AR(1): on every output, the whole unit), "
        "its theta random walk `q` and its declared noise's variance scale `r` chosen "
        "*on the test units themselves* from the grid "
        f"q = {doc['options']['qs']}, r = {doc['options']['rs']}: an oracle "
        "tuning, generous to the filter. Each cell: the best of the grid over the "
        "default UKF's theta RMSE (q = 0.01, r = 1), and the settings that gave it; "
        "`policy`: the default policy over the UKF "
        "(`results/policy_robust/results.json`).",
        "",
        "| model | row | " + " | ".join(labels) + " |",
        "|---|---|" + "---|" * len(labels),
    ]
    for name, res in results.items():
        best = [f"{res[lab]['best_over_ukf']:.2f}" for lab in labels]
        where = [res[lab]["best_settings"].replace(",", ", ") for lab in labels]
        lines.append(f"| {name} | best UKF / UKF | " + " | ".join(best) + " |")
        lines.append("| | its settings | " + " | ".join(where) + " |")
        if name in policy:
            cells = [f"{policy[name].get(lab, float('nan')):.2f}" for lab in labels]
            lines.append("| | policy / UKF | " + " | ".join(cells) + " |")
    lines += ["", *_tradeoffs(results), ""]
    return "\n".join(lines)


def _tradeoffs(results: dict) -> list[str]:
    """Per case, the grid's setting with the lowest worst ratio over the bias, drift
    and gain effects, and what it costs on clean data and under AR(1) noise."""
    faults = ("bias 3σ", "drift 4σ", "gain 3σ")
    lines = [
        "One setting for every effect: the grid's setting whose worst ratio over "
        "the bias, drift and gain is lowest, and its ratio on clean data and under "
        "AR(1) noise (item 3 asks at most 0.5 under each effect and 1.2 clean):",
        "",
        "| model | setting | worst of bias, drift, gain | clean | AR(1) 0.8 |",
        "|---|---|---|---|---|",
    ]
    for name, res in results.items():
        if not all(lab in res for lab in (*faults, "clean", "AR(1) 0.8")):
            continue
        grid = res["clean"]["grid"]

        def ratio(lab, key, res=res):
            return res[lab]["grid"][key] / res[lab]["ukf"]

        key = min(grid, key=lambda k: max(ratio(lab, k) for lab in faults))
        worst = max(ratio(lab, key) for lab in faults)
        lines.append(
            f"| {name} | {key.replace(',', ', ')} | {worst:.2f} | "
            f"{ratio('clean', key):.2f} | {ratio('AR(1) 0.8', key):.2f} |"
        )
    return lines


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
