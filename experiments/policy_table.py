"""Issue 41's table: per model, the policy against the UKF and its own untrained start,
clean and under each effect kind, its deployed cost per row against the UKF's and its
job time, before and after.

    python experiments/policy_table.py [after=results/policy_robust/results.json]
        [before=results/policy_robust/before/results.json]
        [deploy=results/bench/deploy.json]
        [deploy_before=results/bench/deploy_before.json]
        [turbofan=results/policy_any_model/turbofan.json]
        [out=results/policy_any_model/issue41.md]

Reads what ``experiments/policy_robust.py`` (theta RMSE per variant and effect, the
training's gain, job seconds) and ``experiments/bench_deploy.py`` (cost per row, one
stream and a fleet) wrote, and the turbofan's row from what
``experiments/policy_turbofan.py`` wrote (``make train``'s run against the UKF on a
subset of its test rows, its deployed cost); computes nothing new. ``before``: the
same study at the start of the issue's work (commit b0688a7: a 256-wide actor, the
declared noise).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

EFFECTS = ("clean", "bias 3σ", "drift 4σ", "gain 3σ", "AR(1) 0.8")
# bench_deploy names the model as the run records it
DEPLOY_NAMES = {"reactor": "cstr"}
# the rows of a model, in this order (those its results hold)
VARIANTS = (
    "start",
    "rl",
    "clean-tuned",
    "box-2x",
    "actor-tuned",
    "default",
    "effects",
    "theta",
    "both",
)


@dataclasses.dataclass(frozen=True)
class Options:
    """The script's ``key=value`` options (module docstring)."""

    after: str = "results/policy_robust/results.json"
    before: str = "results/policy_robust/before/results.json"
    deploy: str = "results/bench/deploy.json"
    deploy_before: str = "results/bench/deploy_before.json"
    turbofan: str = "results/policy_any_model/turbofan.json"
    out: str = "results/policy_any_model/issue41.md"


def _load(path: str):
    if not path or not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def _fmt(x, digits=2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _ratios(case: dict, variant: str, over: str) -> list[float | None]:
    """The variant's theta RMSE over the UKF's (``over="ukf"``) or over the start's
    (``over="start"``), per effect."""
    runs = case["runs"]
    if variant not in runs:
        return [None] * len(EFFECTS)
    mine = runs[variant]["theta_rmse"]
    base = case["ukf"] if over == "ukf" else runs.get("start", {}).get("theta_rmse")
    if base is None:
        return [None] * len(EFFECTS)
    return [mine[e] / base[e] for e in EFFECTS]


def _deploy(rows, model: str) -> tuple[float | None, float | None]:
    name = DEPLOY_NAMES.get(model, model)
    row = next((r for r in rows or [] if r["model"] == name), None)
    return (None, None) if row is None else (row["stream_ratio"], row["fleet_ratio"])


def table(after: dict, before: dict | None, deploy, deploy_before) -> list[str]:
    head = " | ".join(f"{e}" for e in EFFECTS)
    lines = [
        f"| model | when | variant | x UKF: {head} | x start: {head} "
        "| val gain | job s | cost x UKF: stream | fleet |",
        "|" + "---|" * (3 + 2 * len(EFFECTS) + 4),
    ]
    for model, case in after["results"].items():
        old = (before or {}).get("results", {}).get(model)
        for when, data, rows in (
            ("before", old, deploy_before),
            ("after", case, deploy),
        ):
            if data is None:
                continue
            stream, fleet = _deploy(rows, model)
            for variant in VARIANTS:
                run = data["runs"].get(variant)
                if run is None:
                    continue
                gain = (run.get("training_gain") or {}).get("ratio")
                cells = [
                    model, when, variant,
                    *(_fmt(r) for r in _ratios(data, variant, "ukf")),
                    *(_fmt(r) for r in _ratios(data, variant, "start")),
                    _fmt(gain), f"{run['job_seconds']:.0f}",
                    _fmt(stream) if variant == "start" else "",
                    _fmt(fleet) if variant == "start" else "",
                ]  # fmt: skip
                lines.append("| " + " | ".join(cells) + " |")
    return lines


def turbofan_rows(result: dict | None) -> list[str]:
    """The turbofan's rows (``experiments/policy_turbofan.py``'s JSON): its
    untrained start and ``make train``'s kept policy, after the issue's work."""
    if result is None:
        return []
    job = result["training"]
    gain = job["training_gain"]["ratio"]
    lines = []
    for variant, label, which, seconds in (
        ("start", "start", "theta_rmse", job["start_job_seconds"]),
        ("default", "policy", "theta_rmse", job["job_seconds"]),
        ("default, settled", "policy", "theta_rmse_settled", job["job_seconds"]),
    ):
        mine, ukf, start = (result[which][k] for k in (label, "UKF", "start"))
        cells = [
            "turbofan", "after", variant,
            *(_ratio(mine[e] / ukf[e]) for e in EFFECTS),
            *(_ratio(mine[e] / start[e]) for e in EFFECTS),
            "1.00" if variant == "start" else _ratio(gain), f"{seconds:.0f}",
            _fmt(result["deploy"]["stream_ratio"]) if variant == "start" else "",
            _fmt(result["deploy"]["fleet_ratio"]) if variant == "start" else "",
        ]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _ratio(x: float) -> str:
    """Two decimals, or two significant digits far from 1 (the turbofan's random
    start: thousands of times the UKF's error)."""
    if x >= 100:
        return f"{x:.0f}"
    return f"{x:.2f}" if x >= 0.01 else f"{x:.2g}"


def main(argv: list[str]) -> int:
    from jaxcal.settings import parse_overrides

    try:
        opts = parse_overrides(argv, Options())
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    after = _load(opts.after)
    if after is None:
        print(f"error: no study at {opts.after}", file=sys.stderr)
        return 2
    lines = [
        "# Issue 41: the policy on any model, before and after",
        "",
        f"Generated by `python experiments/policy_table.py` from `{opts.after}` "
        f"(`experiments/policy_robust.py`), `{opts.before}` (the same study at "
        f"b0688a7), `{opts.deploy}` and `{opts.deploy_before}` "
        "(`experiments/bench_deploy.py`). Theta RMSE in box half-widths (mean over "
        "parameters) on the test units 10-12, each effect in every test unit on the "
        "first output from a third of each unit: `x UKF` the policy's over the "
        "UKF's, `x start` over its untrained start's (the extended Kalman filter's "
        "step). `val gain`: the kept policy's simulated-validation theta RMSE over "
        "the start's (1: the start kept). `cost x UKF`: the deployed policy's cost "
        "per row over the UKF's guarded step (one stream, host numpy in and out; a "
        "fleet of 100 units), second calls, interleaved in one process, JAX's "
        "dispatch on the calling thread for both (`synchronous_dispatch`; "
        "`deploy_async.json` the default dispatch); the cost "
        "does not depend on the weights, so it is shown once per model. After: "
        "`start` the untrained policy, `rl` the actor-critic as it was before the "
        "tuning (six chunks, no tuning), `clean-tuned` the default two rounds "
        "before (the actor-critic with patience 2, then `tune.steps=400`: the actor "
        "tuned by gradient through the filter on clean units, docs/policy.md), "
        "`actor-tuned` the default of the round before (the same tuning on units "
        "half of which carry an effect, `tune.effects=0.5`, the units drawn across "
        "the box within 1.5x: results/policy_robust/robust/), `box-2x` that with "
        "them within 2x (`tune.clean_tolerance=1.0`), `default` the default preset "
        "now (the filter's output-bias walks tuned beside the actor, `tune.bias`: "
        "results/policy_robust/bias/). The "
        "turbofan "
        f"(`{opts.turbofan}`, `experiments/policy_turbofan.py`, details in its "
        "`.md`): `default` the run of `make train`, `start` the same with "
        "`budget.num_chunks=0` (a randomly initialised actor: the turbofan's policy "
        "observes no filter step); scored on a subset (each test unit's first and "
        "last rows, each a stream started cold), the effects on its first output "
        "in units of the UKF's declared noise; `settled`: the same runs scored "
        "after each window's first rows (the cold start left out); `val gain` on "
        "the validation tracking RMSE; its cost on its own test rows.",
        "",
        *table(
            after, _load(opts.before), _load(opts.deploy), _load(opts.deploy_before)
        ),
        *turbofan_rows(_load(opts.turbofan)),
        "",
    ]
    os.makedirs(os.path.dirname(opts.out) or ".", exist_ok=True)
    tmp = opts.out + ".tmp"
    with open(tmp, "w") as f:
        f.write("\n".join(lines))
    os.replace(tmp, opts.out)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
