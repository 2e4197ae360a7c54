"""Command line: score a trained run on its test units and measure deployment cost.

Usage::

    python -m jaxcal.evaluate run=runs/<name> [split=test|val] [repeats=500]
    python -m jaxcal.evaluate run=runs/<name> data=<file>
    python -m jaxcal.evaluate run=runs/<feedback run> anchor=runs/<absolute run>
    python -m jaxcal.evaluate run=<received run> trust_code=true

Runs the run's deterministic policy through every unit of the split (the held-out
units the run recorded in ``data.json``; with ``data=``, every unit of that file, whose
columns follow the run's model), whole trajectories (``lax.scan`` over time, vmapped
over units; the deployment calibrator of :mod:`jaxcal.deploy`), and reports the
theta RMSE (pooled and per parameter), the tracking RMSE (normalised, and per
sensor in sensor units) and the deployment cost per sample (paper Table "time"):

* single-stream latency: :meth:`jaxcal.deploy.StreamingCalibrator.step` on one sample
  (host numpy in and out, one jitted call, blocking), median and minimum over
  ``repeats`` consecutive samples of the first unit, after a warm-up call, with
  JAX's dispatch on the calling thread (:func:`jaxcal.deploy.synchronous_dispatch`,
  as a deployed program would run it);
* batched throughput: valid samples per second of the vmapped run over all units of
  the split (median of three timed runs after the compiling one).

Prints the results and writes them to ``runs/<name>/evaluate.json``
(``evaluate_val.json`` for ``split=val``, ``evaluate_<file stem>.json`` for
``data=``). Without a true-parameter column the theta RMSE is not scored. Works for
any model's run (the model is rebuilt from the spec in ``data.json``); x64 is enabled
when the run's model needs it. With ``anchor=`` the run (an incremental policy) is
scored gated by that absolute policy's run
(:mod:`jaxcal.calibrators.methods.policy.gated`; the
report gets ``_gated`` in its name and the anchor's folder). The data file named in
the run's config must be readable, and the run folder writable: a folder that cannot
take the report is an error (exit code 2) before the evaluation starts. A run whose
model is a copy of a model file (or a module) runs that code only with
``trust_code=true``: you trust the folder (``docs/trust.md``).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

from jaxcal.cli.args import parse_command_line
from jaxcal.settings import UnknownKeyError, check_output_path, coerce

USAGE = (
    "usage: python -m jaxcal.evaluate run=runs/<name> [split=test|val] [data=FILE] "
    "[repeats=N] [anchor=runs/<absolute run>] [trust_code=true]"
)
KEYS = ("run", "split", "repeats", "data", "anchor", "trust_code")


def parse_args(argv: list[str]) -> dict:
    """``{"run", "split", "repeats", "data", "anchor", "trust_code"}`` from
    ``key=value`` tokens.

    Raises:
        ValueError: malformed token, unknown key (lists the valid ones), missing run,
            bad split or repeats.
    """
    args: dict[str, str] = {}
    for token in argv:
        key, sep, value = token.partition("=")
        if not sep or not key:
            raise ValueError(f"malformed argument {token!r}: expected key=value")
        if key not in KEYS:
            raise UnknownKeyError(
                f"unknown key {key!r}; valid keys: {', '.join(KEYS)}", key, KEYS
            )
        if key in args:
            raise ValueError(f"key {key!r} given twice")
        args[key] = value
    if not args.get("run"):
        raise ValueError("run=<run folder> is required")
    split = args.get("split", "test")
    if split not in ("test", "val"):
        raise ValueError(f"split must be test or val, got {split!r}")
    try:
        repeats = int(args.get("repeats", "500"))
    except ValueError:
        raise ValueError(
            f"repeats must be an integer, got {args['repeats']!r}"
        ) from None
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    if "data" in args and "split" in args:
        raise ValueError("give split= or data=, not both (data= scores every unit)")
    return {
        "run": args["run"],
        "split": split,
        "repeats": repeats,
        "data": args.get("data") or None,
        "anchor": args.get("anchor") or None,
        "trust_code": coerce(args.get("trust_code", "false"), bool, "trust_code"),
    }


def measure_latency(calibrator, w, x, repeats: int) -> dict:
    """Single-stream seconds per sample of ``calibrator.step`` (blocking, host I/O).

    Args:
        calibrator: a :class:`~jaxcal.deploy.StreamingCalibrator`.
        w, x: ``[T, W]``, ``[T, S]`` samples of one unit, fed in order (cycled).
        repeats: timed calls.

    Returns:
        ``{"median_s", "min_s", "repeats"}``.
    """
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    import numpy as np

    calibrator.reset()
    calibrator.step(w[0], x[0])  # compiles
    times = np.empty(repeats)
    for i in range(repeats):
        t = (i + 1) % len(w)
        tic = time.perf_counter()
        calibrator.step(w[t], x[t])  # returns numpy: the call has finished
        times[i] = time.perf_counter() - tic
    return {
        "median_s": float(np.median(times)),
        "min_s": float(times.min()),
        "repeats": repeats,
        "synchronous": calibrator.synchronous,
    }


def _split_units(run, split: str, data: str | None):
    """The scored units: the run's recorded split, or every unit of ``data``."""
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    from jaxcal.runs.folder import DATA_FILE, read_json
    from jaxcal.training.pipeline import read_run_data

    problem = run.problem
    if data is not None:
        # light --help: imported after the arguments are checked (jaxcal.cli.args)
        from jaxcal.data.readers import read_dataset
        from jaxcal.training.data.tables import pad_units

        rows = read_dataset(data, problem.model).for_model(
            problem.model, problem.output_names
        )
        return pad_units(rows, rows.units, problem.theta_names)
    stored = read_json(run.run_dir / DATA_FILE)
    cfg = dataclasses.replace(
        run.config,
        model=stored.get("model_spec", run.config.model),
        theta=problem.theta_names,
        sensors=problem.output_names,
    )
    # the run's own model (its copy), never the path its model_spec names
    splits = read_run_data(cfg, units=stored["units"], log=print, model=problem.model)
    units = getattr(splits, split)
    if units is None:
        raise ValueError(f"run {run.run_dir} has no {split} units")
    return units


def evaluate_run(
    run_dir: str,
    split: str = "test",
    repeats: int = 500,
    data: str | None = None,
    anchor: str | None = None,
    trust_code: bool = False,
) -> dict:
    """Scores and deployment cost of a run on one split, or on every unit of the
    file ``data``, gated by the run ``anchor`` if given (see the module docstring);
    ``trust_code``: run the runs' model code (``docs/trust.md``)."""
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    import numpy as np

    from jaxcal.deploy import StreamingCalibrator, load_run
    from jaxcal.training.scoring.trajectories import score_units

    run = load_run(run_dir, trust_code=trust_code)
    units = _split_units(run, split, data)
    calibrator = StreamingCalibrator(run, anchor=anchor, trust_code=trust_code)
    theta, xhat, _, reason = calibrator.run(
        units.w, units.x, units.mask, return_flags=True
    )  # compiles
    seconds = []
    for _ in range(3):
        tic = time.perf_counter()
        calibrator.run(units.w, units.x, units.mask)
        seconds.append(time.perf_counter() - tic)
    batch_s = float(np.median(seconds))
    scores = score_units(
        theta,
        xhat,
        units.theta,
        units.x,
        units.mask,
        run.problem.norm.x_std,
        run.problem.output_names,
        run.problem.theta_names,
        reason=reason,  # flagged samples (NaN, far outside training) are counted
    )
    first = units.lengths[0]
    latency = measure_latency(
        calibrator, units.w[0, :first], units.x[0, :first], repeats
    )
    return {
        "run": str(run.run_dir),
        "split": split if data is None else str(data),
        "units": units.unit_ids.tolist(),
        "checkpoint_step": run.step,
        "anchor": None if anchor is None else str(calibrator.anchor_info.run_dir),
        **scores,
        "deployment": {
            "single_stream_latency_s": latency,
            "batched_seconds": batch_s,
            "batched_samples_per_s": units.num_samples / batch_s,
            "batched_units": int(len(units.unit_ids)),
        },
    }


def format_report(report: dict) -> str:
    """Human-readable summary of :func:`evaluate_run`."""
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    from jaxcal.training.scoring.trajectories import describe_units

    dep = report["deployment"]
    lat = dep["single_stream_latency_s"]
    return "\n".join(
        [
            f"{report['run']} (checkpoint {report['checkpoint_step']}), "
            f"{report['split']} units {describe_units(report['units'])}, "
            f"{report['num_samples']:,} samples",
            "theta RMSE: no true parameters to score"
            if report["theta_rmse"] is None
            else f"theta RMSE {report['theta_rmse']:.3e} ("
            + ", ".join(
                f"{k} {v:.3e}" for k, v in report["theta_rmse_per_param"].items()
            )
            + ")",
            f"tracking RMSE {report['tracking_rmse_norm']:.4f} (normalised); in "
            "sensor units: "
            + ", ".join(
                f"{k} {v:.4g}" for k, v in report["tracking_rmse_units"].items()
            ),
            _format_flags(report),
            f"deployment: single-stream {lat['median_s'] * 1e6:.0f} us/sample "
            f"(median, min {lat['min_s'] * 1e6:.0f} us"
            + ("" if lat.get("synchronous", True) else ", JAX's dispatch asynchronous")
            + "); batched "
            f"{dep['batched_samples_per_s']:,.0f} samples/s over "
            f"{dep['batched_units']} units",
        ]
    )


def _format_flags(report: dict) -> str:
    """The line counting flagged (skipped, unscored) samples per reason."""
    flagged = report.get("flagged", {})
    counts = ", ".join(f"{k} {v:,}" for k, v in flagged.items() if v) or "none"
    return (
        f"flagged samples (skipped, not scored): {report.get('num_flagged', 0):,}"
        f" ({counts})"
    )


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 2 bad arguments)."""
    args, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if code is not None:
        return code
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    from jaxcal.cache import enable_compilation_cache
    from jaxcal.calibrators.methods.policy.loading import needs_x64
    from jaxcal.deploy import synchronous_dispatch
    from jaxcal.precision import enable_x64
    from jaxcal.runs.folder import EVALUATION_FILE, write_json

    try:  # before JAX starts: a deployed step's own cost
        synchronous_dispatch()
    except RuntimeError:  # main() called in a process whose JAX has started
        pass  # measured as it runs there; the report says which (synchronous)
    enable_compilation_cache()

    name = EVALUATION_FILE
    if args["data"] is not None:
        stem = os.path.splitext(os.path.basename(args["data"]))[0]
        name = name.replace(".json", f"_{stem}.json")
    elif args["split"] != "test":
        name = name.replace(".json", f"_{args['split']}.json")
    if args["anchor"] is not None:
        name = name.replace(".json", "_gated.json")
    try:
        # The report goes into the run folder: refuse one it cannot go to up front.
        check_output_path(os.path.join(args["run"], name), "run")
        if needs_x64(args["run"]):
            enable_x64()  # before the model loads: its constants take the dtype
        report = evaluate_run(
            args["run"],
            args["split"],
            args["repeats"],
            args["data"],
            args["anchor"],
            trust_code=args["trust_code"],
        )
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    write_json(f"{report['run']}/{name}", report)
    print(format_report(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
