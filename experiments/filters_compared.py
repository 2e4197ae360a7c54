"""The registered filters on the model compared: theta error and cost per row.

Issue 44 asks for an extended Kalman filter as a fifth method, "cheaper than the UKF
on large models". This script measures both halves of that on the policy study's
cases (``experiments/policy_any_model.py``: the same fleets, test units and seeds;
``experiments/policy_robust.py``: the same effects) and on the turbofan:

* **theta error**: ``jaxcal.calibrate`` with each method (the declared noise given,
  the default settings), the RMSE over the valid rows in half-box units, averaged
  over the parameters; the 90 % coverage of the reported std;
* **cost per row** (second calls, compiled, the methods' calls interleaved so that a
  shared machine's load falls on all alike): one stream (each method's guarded step
  jitted as a deployed stream step is,
  :func:`jaxcal.calibrators.programs.packed.jit_per_row`,
  fed one host row at a time; median microseconds) and a fleet (its jitted fleet
  runner over the test units; the best of three).

The turbofan case (``cmapss``) is NASA C-MAPSS FD001's first units with HPC
efficiency and flow declared; it has no truth, so its row gives the cost and the
methods' difference from the UKF's estimate only. Prints JSON and writes it with a
Markdown page beside it.

    python experiments/filters_compared.py cases=heat_exchanger,pump,reactor,cmapss
"""

from __future__ import annotations

import dataclasses
import json
import os
import shlex
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

Z90 = 1.6448536269514722


@dataclasses.dataclass(frozen=True)
class Options:
    """The script's ``key=value`` options (module docstring)."""

    cases: str = "heat_exchanger,pump,motor,fan,reactor,cmapss"
    methods: str = "ukf,ekf"
    effects: str = "clean,bias 3σ,AR(1) 0.8"
    rows: int = 300  # rows a stream is timed on
    data: str = "data/policy_robust"
    out: str = "results/methods/filters_compared.json"
    seed: int = 0


def _cmapss():
    """The turbofan case: FD001's first 10 units, no truth, the noise estimated."""
    import jaxcal

    path = os.path.join(HERE, "..", "..", "shared", "data", "cmapss", "train_FD001.txt")
    data = jaxcal.read_dataset(path, jaxcal.models.load("cmapss"))
    return "cmapss", data.select_units(range(1, 11)), ["HPC_eff_mod", "HPC_flow_mod"]


def _theta_scores(res, frame, theta, half) -> dict:
    ok = np.asarray(res.valid, bool)
    if not hasattr(frame, "columns"):  # a data set without the truth
        return {"valid": float(ok.mean())}
    err = (res.theta - frame[theta].to_numpy()) / half
    out = {"rmse": float(np.mean(np.sqrt(np.mean(err[ok] ** 2, axis=0))))}
    if res.theta_std is not None:
        std = res.theta_std / half
        shown = ok & np.isfinite(std).all(axis=1)
        out["coverage90"] = float(np.mean(np.abs(err[shown]) <= Z90 * std[shown]))
    return out


def _costs(problem, data, names, rows) -> dict:
    """Stream and fleet microseconds per row of each method (module docstring)."""
    import functools

    import jax
    from bench_deploy import _per_row

    from jaxcal.calibrators import methods
    from jaxcal.calibrators.guard import guarded_update, initial_carry, sample_reason
    from jaxcal.calibrators.interface import run_fleet
    from jaxcal.calibrators.programs.packed import jit_per_row
    from jaxcal.data.buckets import bucket_units

    model = problem.model
    data = data.for_model(model, problem.output_names)
    part = bucket_units(data, np.float64).parts[0]
    w, x = np.asarray(part.w), np.asarray(part.x)
    rows = min(rows, w.shape[1])
    streams, fleets = {}, {}
    for name in names:
        cfg = methods.config(name, {})
        method = methods.get(name)
        cal, check = method.make(problem, cfg), method.check(problem, cfg)

        @functools.partial(jit_per_row, warm_solve=model.warm_size > 0)
        def step(carry, w_t, x_t, cal=cal, check=check):
            reason = sample_reason(check, w_t, x_t)
            return guarded_update(cal.step, carry, w_t, x_t, reason)

        w0, x0 = jax.numpy.asarray(w[0, 0]), jax.numpy.asarray(x[0, 0])
        carry = [initial_carry(cal.step, cal.init(None, w0, x0), w0, x0)]

        def one(t, step=step, carry=carry):
            carry[0], res, reason = step(carry[0], w[0, t], x[0, t])
            jax.device_get((res.theta, reason))

        streams[name] = one
        fleet = jax.jit(lambda w_, x_, m_, cal=cal, check=check: run_fleet(
            cal, w_, x_, m_, check=check))  # fmt: skip
        fleets[name] = functools.partial(fleet, w, x, np.asarray(part.mask))
    out = {"stream": _per_row(streams, rows), "fleet_us_per_row": {}}
    for fn in fleets.values():
        jax.block_until_ready(fn())  # compiled
    best = dict.fromkeys(fleets, np.inf)
    for _ in range(3):
        for name, fn in fleets.items():
            tic = time.perf_counter()
            jax.block_until_ready(fn())
            best[name] = min(best[name], time.perf_counter() - tic)
    valid = int(np.asarray(part.mask).sum())
    out["fleet_us_per_row"] = {k: 1e6 * v / valid for k, v in best.items()}
    return out


def run_case(name: str, opts: Options) -> dict:
    import jaxcal

    noise, effects = None, ["clean"]
    if name == "cmapss":
        spec, test, theta = _cmapss()
    else:
        from policy_any_model import _case, split_files
        from policy_robust import EFFECTS, with_effect

        spec, fleet, theta, noise = _case(name, opts.seed)
        _, test = split_files(name, spec, fleet, opts.data)
        effects = opts.effects.split(",")
    model = jaxcal.models.load(spec)
    low, high = model.bounds
    index = [model.parameter_names.index(t) for t in theta]
    half = 0.5 * (high[index] - low[index])
    names = opts.methods.split(",")
    out = {"model": spec, "theta": theta, "effects": {}}
    problem = None
    if noise is None:  # the turbofan: every method given the noise a UKF estimates
        problem = jaxcal.calibrate(spec, test, theta=theta, progress=False).problem
        noise = dict(zip(problem.output_names, problem.noise_std.tolist(), strict=True))
    for label in effects:
        frame = test
        if label != "clean":
            outputs = [o for o in model.output_names if o in noise]
            kind, size = EFFECTS[label]
            rng = np.random.default_rng(7)  # the policy study's frames
            frame = with_effect(test, outputs, noise, kind, size, rng)
        per, thetas = {}, {}
        for method in names:
            res = jaxcal.calibrate(
                spec, frame, method=method, theta=theta, noise=noise,
                progress=False, misfit="keep",
            )  # fmt: skip
            if problem is None:  # the clean data's (the turbofan: noise estimated)
                problem = res.problem
                noise = dict(
                    zip(problem.output_names, problem.noise_std.tolist(), strict=True)
                )
            per[method] = _theta_scores(res, frame, theta, half)
            thetas[method] = res.theta
        for method in names[1:]:
            diff = np.abs(thetas[method] - thetas[names[0]]) / half
            per[method]["max_diff_from_" + names[0]] = float(np.nanmax(diff))
        out["effects"][label] = per
        print(name, label, json.dumps(per), flush=True)
    data = test if name == "cmapss" else jaxcal.read_dataset(test, model)
    out["rows"] = int(data.num_rows)
    out["cost"] = _costs(problem, data, names, opts.rows)
    print(name, "cost", json.dumps(out["cost"]), flush=True)
    return out


def _page(doc: dict, names: list[str]) -> str:
    """The Markdown page of a run: theta error and cost, each method against the
    first (the UKF)."""
    ref, others = names[0], names[1:]
    lines = [
        "# The registered filters on the model compared",
        "",
        f"Command: `{doc['command']}` (`experiments/filters_compared.py`; 2 cores).",
        "",
        "Theta RMSE in half-box units over the valid rows (mean over the declared",
        "parameters), the 90 % coverage of the reported std, on the policy study's",
        "test units with the declared noise given; the turbofan (NASA FD001, units",
        "1-10, HPC efficiency and flow) has no truth: its row gives the largest",
        f"difference from the {ref.upper()}'s estimate instead.",
        "",
        "| case | data | "
        + " | ".join(f"{m.upper()} RMSE (cov.)" for m in names)
        + " | "
        + " | ".join(f"{m.upper()} / {ref.upper()}" for m in others)
        + " |",
        "|---" * (2 + len(names) + len(others)) + "|",
    ]
    for case, res in doc["cases"].items():
        for label, per in res["effects"].items():
            cells = []
            for m in names:
                if "rmse" in per[m]:
                    cov = per[m].get("coverage90")
                    cells.append(f"{per[m]['rmse']:.4f} ({cov:.2f})")
                else:
                    cells.append(f"valid {per[m]['valid']:.2f}")
            for m in others:
                if "rmse" in per[m]:
                    cells.append(f"{per[m]['rmse'] / per[ref]['rmse']:.2f}")
                else:
                    cells.append(f"max diff {per[m]['max_diff_from_' + ref]:.3f}")
            lines.append(f"| {case} | {label} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Cost per row, second calls (compiled), the methods interleaved: one stream",
        "(the guarded step jitted as a deployed stream step, fed one host row at a",
        "time; median µs) and the fleet of test units (jitted fleet runner; the best",
        "of three, µs per valid row).",
        "",
        "| case | rows | "
        + " | ".join(f"{m.upper()} stream" for m in names)
        + " | "
        + " | ".join(f"{m.upper()} fleet" for m in names)
        + " | "
        + " | ".join(f"{m.upper()} / {ref.upper()} stream, fleet" for m in others)
        + " |",
        "|---" * (2 + 2 * len(names) + len(others)) + "|",
    ]
    for case, res in doc["cases"].items():
        stream, fleet = res["cost"]["stream"], res["cost"]["fleet_us_per_row"]
        cells = [f"{stream[m]['median_us']:.0f}" for m in names]
        cells += [f"{fleet[m]:.1f}" for m in names]
        cells += [
            f"{stream[m]['median_us'] / stream[ref]['median_us']:.2f}, "
            f"{fleet[m] / fleet[ref]:.2f}"
            for m in others
        ]
        lines.append(f"| {case} | {res['rows']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    from jaxcal.precision import enable_x64
    from jaxcal.settings import parse_overrides

    enable_x64()  # the turbofan's Newton solve and the filters' covariances

    opts = parse_overrides(argv, Options())
    doc = {"command": "python experiments/filters_compared.py " + shlex.join(argv)}
    doc["cases"] = {name: run_case(name, opts) for name in opts.cases.split(",")}
    os.makedirs(os.path.dirname(opts.out) or ".", exist_ok=True)
    with open(opts.out, "w") as f:
        json.dump(doc, f, indent=1)
    with open(os.path.splitext(opts.out)[0] + ".md", "w") as f:
        f.write(_page(doc, opts.methods.split(",")))
    print(json.dumps(doc)[:2000])
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
