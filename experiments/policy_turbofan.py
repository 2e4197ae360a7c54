"""Issue 41's turbofan row: the trained turbofan policy (``make train``) against the
UKF and its own untrained start, clean and under each effect kind, its deployed cost
per row against the UKF's, and what training gained over the start.

    python experiments/policy_turbofan.py [run=runs/cmapss_q41]
        [start=runs/cmapss_start41] [rows=1500] [settle=300] [sensor=] [bench_rows=200]
        [bench_units=16] [bench_block=1] [sync=true]
        [out=results/policy_any_model/turbofan.json]

``start``: the same training with ``budget.num_chunks=0`` (the untrained policy the
run starts from: on the turbofan a randomly initialised actor, ``env.gauss_newton=
off``, not a filter's step). Scored on a subset, the UKF being slow (a Newton solve
at every sigma point): each test unit's first and last ``rows`` rows, each window a
stream started cold (the UKF at the box centre, the policy at its start), so that
the set holds the early, slowly degrading life and the late, fast one. The
policies and the paper's UKF on F (q = r = 0.01 on outputs in units of their
training std, :mod:`jaxcal.paper.methods`) run over the same windows, clean and with
one effect of :data:`TURBOFAN_EFFECTS` in every window (bias, drift and gain on
``sensor``, default the first output, from a third of the window; AR(1) noise on
every output, the whole window; white noise on every output, the whole window: the
clean case of a measured stream), in units of the UKF's declared noise std (``r``
times the output's training std: the generated data carry no noise of their own).
Scored by theta RMSE over each method's unflagged rows, and ``settled``: over each
window's rows from ``settle`` on (the cold start's transient left out).

Deployed cost: :func:`bench_deploy.bench_run` on ``bench_units`` streams of
``bench_rows`` test rows (windows spread over the test units), the policy's
``StreamingCalibrator`` against the method table's UKF on the run's problem,
interleaved in one process; ``sync=true`` (the default) with JAX's calls on the
calling thread (:func:`jaxcal.deploy.synchronous_dispatch`), as
``bench_deploy.py``. Writes ``out`` and the page beside it (``.md``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from bench_deploy import bench_run  # noqa: E402
from policy_robust import EFFECTS  # noqa: E402

METHODS = {"UKF": "UKF", "policy": "CLAC", "start": "start"}  # label: suite name
# the generated data carry no noise: white noise of the declared std on every
# output (an AR(1) of coefficient 0) is the clean case of a measured stream
TURBOFAN_EFFECTS = {**EFFECTS, "white 1σ": ("ar1", 0.0)}


@dataclasses.dataclass(frozen=True)
class Options:
    """The script's ``key=value`` options (module docstring)."""

    run: str = "runs/cmapss_q41"
    start: str = "runs/cmapss_start41"
    rows: int = 1500
    settle: int = 300
    sensor: str = ""
    bench_rows: int = 200
    bench_units: int = 16
    bench_block: int = 1  # the stream calls interleaved in blocks of this many rows
    sync: bool = True
    out: str = "results/policy_any_model/turbofan.json"


def windows(units, rows: int):
    """``Padded`` of each unit's first and last ``rows`` rows (``unit_ids``: the
    unit, negative for its last window), every window ``rows`` long."""
    from jaxcal.data.padded import Padded

    lives = zip(units.unit_ids, units.lengths, strict=True)
    short = [int(u) for u, n in lives if n < 2 * rows]
    if short:
        raise ValueError(f"test units {short} have fewer than 2 x rows={rows} rows")
    parts = {"w": [], "x": [], "theta": []}
    ids = []
    for i, (uid, n) in enumerate(zip(units.unit_ids, units.lengths, strict=True)):
        for sign, cut in ((1, slice(0, rows)), (-1, slice(n - rows, n))):
            for name in parts:
                parts[name].append(getattr(units, name)[i, cut])
            ids.append(sign * int(uid))
    return Padded(
        *(np.stack(parts[k]) for k in ("w", "x", "theta")),
        lengths=np.full(len(ids), rows, np.int32),
        unit_ids=np.asarray(ids),
    )


def with_effect(x: np.ndarray, out: int, sd: np.ndarray, kind: str, size, rng):
    """``x [U, T, S]`` with ``kind`` in every window (:data:`TURBOFAN_EFFECTS`,
    in units of ``sd [S]``): bias, drift, gain on output ``out`` from a third of the
    window, AR(1) noise of ``sd`` on every output, the whole window (coefficient
    ``size``; 0: white noise)."""
    x = x.copy()
    steps = x.shape[1]
    ramp = np.zeros(steps)
    ramp[steps // 3 :] = 1.0
    if kind == "bias":
        x[:, :, out] += size * sd[out] * ramp
    elif kind == "drift":
        ramp[steps // 3 :] = np.linspace(0, 1, steps - steps // 3)
        x[:, :, out] += size * sd[out] * ramp
    elif kind == "gain":
        level = np.mean(np.abs(x[:, :, out]), axis=1, keepdims=True)
        x[:, :, out] += size * sd[out] / level * x[:, :, out] * ramp
    elif kind == "ar1":
        e = rng.normal(size=x.shape) * sd
        ar = np.empty_like(e)
        ar[:, 0] = e[:, 0]
        for t in range(1, steps):  # an experiment's data, host side
            ar[:, t] = size * ar[:, t - 1] + np.sqrt(1 - size**2) * e[:, t]
        x += ar
    elif kind != "none":
        raise ValueError(f"unknown effect kind {kind!r}")
    return x


def bench_rows_of(units, streams: int, rows: int):
    """``(w, x)`` of ``streams`` windows of ``rows`` test rows, spread evenly over
    the units' lives (the costs of the turbofan depend on its operating point)."""
    per_unit = -(-streams // len(units.lengths))
    w, x = [], []
    for i, n in enumerate(units.lengths):
        for start in np.linspace(0, int(n) - rows, per_unit).astype(int):
            w.append(units.w[i, start : start + rows])
            x.append(units.x[i, start : start + rows])
    return np.stack(w[:streams]), np.stack(x[:streams])


def _read(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def training(run: str, start: str) -> dict:
    """The trained run's job and scores, and its gain over the untrained start on
    its selection's validation score (the start run's chunk 0 beside the kept
    chunk: ``training_gain`` as ``final.json`` reports it since issue 41)."""
    final = _read(os.path.join(run, "final.json"))
    begin = _read(os.path.join(start, "final.json"))
    tracking = final["select"] == "val_tracking"
    key = "tracking_rmse_norm" if tracking else "sim_theta_rmse"
    kept, untrained = final["val_selected"][key], begin["val_selected"][key]
    return {
        "job_seconds": final.get("wall_seconds_total", final["wall_seconds"]),
        "chunks": final["chunks"],
        "selected_chunk": final["selected_chunk"],
        "test_theta_rmse_all_rows": final["test"]["theta_rmse"],
        "test_coverage90": final.get("test_coverage90"),
        "start_job_seconds": begin["wall_seconds"],
        "start_test_theta_rmse_all_rows": begin["test"]["theta_rmse"],
        "training_gain": {
            "key": f"val_{key}",
            "start": untrained,
            "kept": kept,
            "ratio": kept / untrained,
            "start_is": "a randomly initialised actor (env.gauss_newton=off)",
            "run_reported": final.get("training_gain") or None,
        },
    }


def score(opts: Options) -> dict:
    from jaxcal.paper.compare import evaluate_method
    from jaxcal.paper.suite import Suite, SuiteConfig

    data = _read(os.path.join(opts.run, "final.json"))["data"]
    suite = Suite(
        data, {"CLAC": opts.run, "start": opts.start}, SuiteConfig(), "/nonexistent"
    )
    problem = suite.problem
    units = windows(suite.data.test, opts.rows)
    names = list(problem.output_names)
    sensor = opts.sensor or names[0]
    if sensor not in names:
        raise ValueError(f"sensor={sensor!r} is not an output of the run: {names}")
    sd = suite.cfg.ukf.r * np.asarray(problem.norm.x_std, np.float64)
    result = {
        "subset": f"test units {sorted(set(abs(units.unit_ids).tolist()))}: the first "
        f"and the last {opts.rows} rows of each, {len(units.lengths)} streams "
        "started cold",
        "effect_output": sensor,
        "effect_sd": float(sd[names.index(sensor)]),
        "theta": list(problem.theta_names),
        "theta_half_width": problem.theta_half_width.tolist(),
        "theta_rmse": {label: {} for label in METHODS},
        "theta_rmse_settled": {label: {} for label in METHODS},
        "theta_rmse_per_window": {label: {} for label in METHODS},
        "flagged": {label: {} for label in METHODS},
        # the share of rows inside each method's 90 % band (None: no band)
        "coverage90": {label: {} for label in METHODS},
        "seconds": {label: 0.0 for label in METHODS},
    }
    for effect, (kind, size) in TURBOFAN_EFFECTS.items():
        x = with_effect(
            units.x, names.index(sensor), sd, kind, size, np.random.default_rng(7)
        )
        frame = units._replace(x=x)
        for label, name in METHODS.items():
            tic = time.perf_counter()
            run = evaluate_method(suite.method(name), frame, problem)
            result["seconds"][label] += time.perf_counter() - tic
            result["theta_rmse"][label][effect] = run.scores["theta_rmse"]
            late = run.theta[:, opts.settle :] - frame.theta[:, opts.settle :]
            settled = float(np.sqrt(np.nanmean(late**2)))
            result["theta_rmse_settled"][label][effect] = settled
            per_window = run.scores["theta_rmse_per_unit"]
            result["theta_rmse_per_window"][label][effect] = per_window
            result["flagged"][label][effect] = run.scores.get("num_flagged", 0)
            result["coverage90"][label][effect] = run.scores.get("coverage90")
            print(effect, label, f"{run.scores['theta_rmse']:.4g}", flush=True)
    w, x = bench_rows_of(suite.data.test, opts.bench_units, opts.bench_rows)
    result["deploy"] = bench_run(
        opts.run,
        opts.bench_rows,
        opts.bench_units,
        data=(w, x),
        block=opts.bench_block,
    )
    return result


def page(result: dict, opts: Options) -> str:
    ukf = result["theta_rmse"]["UKF"]
    gain = result["training"]["training_gain"]
    dep = result["deploy"]
    head = " | ".join(TURBOFAN_EFFECTS)
    settled_rows = [
        f"| {label}, settled | "
        + " | ".join(
            f"{scores[e]:.3g}"
            + (
                ""
                if label == "UKF"
                else f" ({scores[e] / result['theta_rmse_settled']['UKF'][e]:.2f}x)"
            )
            for e in TURBOFAN_EFFECTS
        )
        + " |"
        for label, scores in result["theta_rmse_settled"].items()
    ]
    clean = {
        label: {
            part: float(np.sqrt(np.mean([v**2 for k, v in win["clean"].items() if
                                         (int(k) > 0) == (part == "first")])))
            for part in ("first", "last")
        }
        for label, win in result["theta_rmse_per_window"].items()
    }  # fmt: skip
    lines = [
        "# The turbofan's policy against the UKF and its untrained start (issue 41)",
        "",
        f"`python experiments/policy_turbofan.py run={opts.run} start={opts.start} "
        f"rows={opts.rows} bench_rows={opts.bench_rows} "
        f"bench_units={opts.bench_units}` ({result['load']}). Subset: "
        f"{result['subset']}. Effects on {result['effect_output']} (AR(1): every "
        f"output) in units of the UKF's declared noise std (r = 0.01 of each "
        f"output's training std; {result['effect_output']}: "
        f"{result['effect_sd']:.4g}). Theta RMSE of HPT_eff_mod over each "
        f"method's unflagged rows ({_flagged(result)}), `(x)` over the UKF's; "
        "`policy` the run's kept policy, `start` its untrained "
        "start (a randomly initialised actor: the turbofan's policy observes no "
        "filter step, `env.gauss_newton=off`).",
        "",
        f"| method | {head} |",
        "|---|" + "---|" * len(TURBOFAN_EFFECTS),
    ]
    for label, scores in result["theta_rmse"].items():
        lines.append(
            f"| {label} | "
            + " | ".join(
                f"{scores[e]:.3g}"
                + ("" if label == "UKF" else f" ({scores[e] / ukf[e]:.2f}x)")
                for e in TURBOFAN_EFFECTS
            )
            + " |"
        )
    lines += settled_rows
    lines += [
        "",
        f"`settled`: from row {opts.settle} of each window on. Clean, whole "
        "windows, the first (early life) and the last (late life) apart: "
        + "; ".join(
            f"{label} {v['first']:.3g} and {v['last']:.3g}"
            for label, v in clean.items()
        )
        + ".",
    ]
    job = result["training"]
    lines += [
        "",
        f"Training: {job['job_seconds']:.0f} s of job wall time, {job['chunks']} "
        f"chunks, kept chunk {job['selected_chunk']} (all test rows: theta RMSE "
        f"{job['test_theta_rmse_all_rows']:.3g}, 90 % band coverage "
        f"{job['test_coverage90']:.3f}); its gain over the untrained start on the "
        f"validation {gain['key'][4:]}: {gain['start']:.3g} -> {gain['kept']:.3g} "
        f"({gain['ratio']:.2g}x; the start run: {job['start_job_seconds']:.0f} s, "
        f"all test rows theta RMSE {job['start_test_theta_rmse_all_rows']:.3g}).",
        "",
        f"Deployed cost per row ({dep['units']} streams x {dep['rows']} test rows, "
        "interleaved in one process, JAX's dispatch "
        + ("on the calling thread" if dep.get("synchronous") else "by its thread pool")
        + "): one stream "
        f"`StreamingCalibrator.step` {dep['policy_stream']['median_us']:.0f} µs "
        f"(p95 {dep['policy_stream']['p95_us']:.0f}) against the UKF's guarded step "
        f"{dep['ukf_stream']['median_us']:.0f} µs (p95 "
        f"{dep['ukf_stream']['p95_us']:.0f}): **{dep['stream_ratio']:.2f}x**; fleet "
        f"{dep['policy_fleet_us_per_row']:.1f} µs against "
        f"{dep['ukf_fleet_us_per_row']:.1f} µs a row: "
        f"**{dep['fleet_ratio']:.2f}x**.",
        "",
    ]
    return "\n".join(lines)


def _flagged(result: dict) -> str:
    """How many rows each method flagged, summed over the effects."""
    counts = {k: sum(v.values()) for k, v in result["flagged"].items()}
    if not any(counts.values()):
        return "none flagged"
    return "flagged: " + ", ".join(f"{k} {v}" for k, v in counts.items())


def _load() -> str:
    one, five, _ = os.getloadavg()
    return f"2 cores, load average {one:.1f} (5 min {five:.1f}) at the end"


def main(argv: list[str]) -> int:
    from jaxcal.settings import parse_overrides

    try:
        opts = parse_overrides(argv, Options())
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    import jax

    if opts.sync:
        from jaxcal.deploy import synchronous_dispatch

        synchronous_dispatch()  # before any JAX computation
    jax.config.update("jax_enable_x64", True)  # entry point: the turbofan's F
    tic = time.perf_counter()
    result = {"options": dataclasses.asdict(opts)}
    result["training"] = training(opts.run, opts.start)
    result.update(score(opts))
    result["seconds_total"] = time.perf_counter() - tic
    result["load"] = _load()
    from jaxcal.runs.atomic import write_atomic
    from jaxcal.runs.folder import write_json

    os.makedirs(os.path.dirname(opts.out) or ".", exist_ok=True)
    write_json(opts.out, result)
    write_atomic(os.path.splitext(opts.out)[0] + ".md", page(result, opts))
    print(page(result, opts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
