"""The battery example end to end: PyBaMM data, every calibrator, dynamax and PyBOP.

    python examples/battery/run.py [out=DIR] [data=DIR] [runs=DIR] [chunks=N]
                                   [skip=ls,policy,...]      (or: make battery)

1. writes the PyBaMM fleet if missing (``make_data.py``: 4 cells x 20 cycles);
2. calibrates ``R0`` and ``Q`` of every cell with ``jaxcal.calibrate(MODEL, data,
   method)`` for ukf, ls, e2e, and policy (trained first by ``python -m
   jaxcal.train model=examples/battery/model.py:MODEL ...``);
3. runs dynamax's UKF on the same ECM, data and settings, and PyBOP's per-cycle fit;
4. measures throughput (samples/s, one stream and a fleet of 64 streams) of jaxcal's
   UKF and dynamax's after compilation, in this one run;
5. writes ``README.md``, ``results.json``, ``tracking.png`` and ``bench.png`` to
   ``out`` (default ``results/examples/battery``).

Scores: RMSE of the tracked R0 [Ohm] and Q [Ah] against ``R0_true`` / ``Q_true``
(defined in ``make_data.py``) over every valid row from cycle 1 on (cycle 0 is the
filters' settling); PyBOP's per-cycle values are held over their cycle.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import traceback

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

METHODS = ("ukf", "ls", "e2e", "policy")
POLICY_TEST_UNITS = (3, 4)  # the policy is trained on units 1-2
NAME = "battery-example"
FLEET_SIZE = 64
BENCH_STEPS = 2000


def _args(argv):
    opts = {"out": "results/examples/battery", "data": "data/battery",
            "runs": "runs", "chunks": "", "skip": ""}  # fmt: skip
    for token in argv:
        key, sep, value = token.partition("=")
        if not sep or key not in opts:
            raise SystemExit(f"usage: run.py [{'] ['.join(f'{k}=...' for k in opts)}]; got {token!r}")  # fmt: skip
        opts[key] = value
    opts["skip"] = {s for s in opts["skip"].split(",") if s}
    return opts


def _score(theta, frame, valid=None) -> dict:
    """RMSE of ``theta [N, 2]`` (R0, Q) against the truth, cycles >= 1."""
    keep = frame.cycle.to_numpy() >= 1
    if valid is not None:
        keep &= valid
    err = theta[keep] - frame[["R0_true", "Q_true"]].to_numpy()[keep]
    rmse = np.sqrt(np.mean(err**2, axis=0))
    return {"R0": float(rmse[0]), "Q": float(rmse[1]), "rows": int(keep.sum())}


def _method_options(method: str, opts: dict) -> dict:
    from peers import UKF

    if method == "ukf":
        return {k: UKF[k] for k in ("q", "prior_std", "state_std", "state_q")}
    if method == "ls":
        # an hour of samples: the state of charge moves enough to show capacity
        # (a 10-minute window, 10 iterations: Q RMSE 0.91 Ah, measured)
        return {"window": 360, "num_iters": 3}
    if method == "policy":
        return {"run": os.path.join(opts["runs"], NAME)}
    return {}


def _train_policy(csv: str, opts: dict) -> float:
    """Train the tracking policy by the command line; returns its training seconds."""
    from peers import THETA, UKF

    units = ",".join(str(u) for u in POLICY_TEST_UNITS)
    command = [
        sys.executable, "-m", "jaxcal.train",
        f"model={os.path.join(HERE, 'model.py')}:MODEL", f"data={csv}",
        f"theta={','.join(THETA)}", f"test_units={units}", f"name={NAME}",
        f"output.runs_dir={opts['runs']}",
        # the noise the UKF is given: 2 mV sensor + ~18 mV ECM-vs-SPMe model error
        f"noise={UKF['noise']}",
        # and its random walk and prior: the policy's filter step is the UKF's
        f"env.filter_q={UKF['q']}", f"env.filter_prior_std={UKF['prior_std']}",
        *([f"budget.num_chunks={opts['chunks']}"] if opts["chunks"] else []),
    ]  # fmt: skip
    print("$ " + " ".join(command[1:]), flush=True)
    subprocess.run(command, check=True)
    with open(os.path.join(opts["runs"], NAME, "final.json")) as f:
        return float(json.load(f)["train_seconds"])


def run_jaxcal(frame, csv: str, opts: dict) -> tuple[dict, dict]:
    """Every jaxcal method: ``(summary per method, theta [N, 2] per method)``."""
    from peers import THETA, UKF

    import jaxcal

    # named through jaxcal.models.load, the model is consented to (docs/trust.md):
    # the policy's run holds a copy of the same file, which then loads
    MODEL = jaxcal.models.load(f"{os.path.join(HERE, 'model.py')}:MODEL")

    summary, tracks = {}, {}
    for method in METHODS:
        if method in opts["skip"]:
            summary[method] = {"error": "skipped (skip=)"}
            continue
        print(f"jaxcal {method} ...", flush=True)
        try:
            extra = {}
            if method == "policy":
                extra["train_seconds"] = _train_policy(csv, opts)
            start = time.perf_counter()
            res = jaxcal.calibrate(
                MODEL, csv, method=method, theta=THETA,
                noise={"voltage": UKF["noise"]}, **_method_options(method, opts),
            )  # fmt: skip
            wall = time.perf_counter() - start
        except Exception as exc:  # one method failing must not hide the others
            traceback.print_exc()
            summary[method] = {"error": f"{type(exc).__name__}: {str(exc)[:400]}"}
            continue
        tracks[method] = res.theta
        summary[method] = {
            **_score(res.theta, frame, res.valid), **extra,
            "wall_s": wall, "us_per_sample": wall / len(frame) * 1e6,
            "flagged": int((~res.valid).sum()),
        }  # fmt: skip
        print(f"  {method}: {summary[method]}", flush=True)
    return summary, tracks


def run_dynamax(frame) -> tuple[dict, np.ndarray | None]:
    """dynamax's UKF per unit (vmapped over the units, padded to one length)."""
    try:
        import jax
        import jax.numpy as jnp
        from peers import make_dynamax_filter, time_per_sample

        track = make_dynamax_filter()
        start = time.perf_counter()
        theta = np.zeros((len(frame), 2))
        for unit in np.unique(frame.unit):  # one compile: same length per unit
            rows = (frame.unit == unit).to_numpy()
            args = [jnp.asarray(frame.loc[rows, c].to_numpy()) for c in ("current", "dt", "voltage")]  # fmt: skip
            mean, _ = jax.jit(track)(*args)
            theta[rows] = np.asarray(mean)[:, 2:]
        wall = time.perf_counter() - start
        one = [jnp.asarray(frame.loc[frame.unit == 1, c].to_numpy()) for c in ("current", "dt", "voltage")]  # fmt: skip
        per_sample = time_per_sample(jax.jit(track), *one) / len(one[0])
    except Exception as exc:  # an optional peer
        traceback.print_exc()
        return {"error": f"{type(exc).__name__}: {str(exc)[:400]}"}, None
    import dynamax

    out = {**_score(theta, frame), "wall_s": wall, "us_per_sample": per_sample * 1e6,
           "version": getattr(dynamax, "__version__", "?")}  # fmt: skip
    print(f"  dynamax: {out}", flush=True)
    return out, theta


def run_pybop(frame) -> tuple[dict, np.ndarray | None]:
    """PyBOP's per-cycle fit on every unit; its values held over each cycle."""
    from peers import pybop_fit

    theta = np.full((len(frame), 2), np.nan)
    seconds, version = [], None
    for unit in np.unique(frame.unit):
        rows = frame[frame.unit == unit]
        fit = pybop_fit(rows, np.unique(rows.cycle))
        if "error" in fit:
            print(f"  pybop: {fit['error']}", flush=True)
            return {"error": fit["error"]}, None
        version = fit["version"]
        for k, r0, q in zip(fit["cycle"], fit["R0"], fit["Q"], strict=True):
            sel = ((frame.unit == unit) & (frame.cycle == k)).to_numpy()
            theta[sel] = (r0, q)
        seconds += fit["seconds"]
    out = {**_score(theta, frame), "wall_s": float(np.sum(seconds)),
           "s_per_cycle": float(np.mean(seconds)),
           "us_per_sample": float(np.sum(seconds)) / len(frame) * 1e6,
           "version": version}  # fmt: skip
    print(f"  pybop: {out}", flush=True)
    return out, theta


def main(argv: list[str]) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)  # entry point: the filters want float64
    import make_data
    import pandas as pd
    from bench import run_bench
    from figures import bench_figure, tracking_figure
    from page import write_page

    opts = _args(argv)
    os.makedirs(opts["out"], exist_ok=True)
    frame = pd.read_csv(make_data.main([f"out={opts['data']}"]))
    # jaxcal's readers take the model's columns only; the truths under the
    # parameters' names are the "true parameters" its CLI scores against
    csv = os.path.join(opts["data"], "fleet_jaxcal.csv")
    columns = {"R0_true": "R0", "Q_true": "Q"}
    frame[["unit", "time", "current", "dt", "voltage", *columns]].rename(columns=columns).to_csv(csv, index=False)  # fmt: skip
    print(f"data: {len(frame)} rows, units {sorted(set(frame.unit))}", flush=True)
    summary, tracks = run_jaxcal(frame, csv, opts)
    print("dynamax UKF ...", flush=True)
    summary["dynamax"], tracks_dx = run_dynamax(frame)
    print("PyBOP per-cycle fits ...", flush=True)
    summary["pybop"], tracks_pb = run_pybop(frame) if "pybop" not in opts["skip"] else ({"error": "skipped (skip=)"}, None)  # fmt: skip
    for name, theta in (("dynamax", tracks_dx), ("pybop", tracks_pb)):
        if theta is not None:
            tracks[name] = theta
    print("throughput (after compilation) ...", flush=True)
    bench = run_bench(frame, FLEET_SIZE, BENCH_STEPS)
    results = {"methods": summary, "bench": bench, "rows": len(frame),
               "units": int(frame.unit.nunique()),
               "cycles": int(frame.cycle.nunique())}  # fmt: skip
    with open(os.path.join(opts["out"], "results.json"), "w") as f:
        json.dump(results, f, indent=2)
    tracking_figure(frame, tracks, os.path.join(opts["out"], "tracking.png"))
    bench_figure(bench, os.path.join(opts["out"], "bench.png"))
    write_page(results, opts["out"])
    print(f"results in {opts['out']}/README.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
