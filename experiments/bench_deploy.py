"""The deployed policy's cost per row against the UKF's, one stream and a fleet
(issue 41 item 2), on trained runs of any model.

    python experiments/bench_deploy.py runs=<run>[,<run>...] [rows=400] [units=100]
        [sync=true] [block=1] [out=results/bench/deploy.json]

Per run, second calls (compiled), this machine's 2 cores, as ratios in one process
(the two methods' calls interleaved, so that a shared machine's load falls on both:
row by row, or in blocks of ``block`` rows):

* one stream: ``StreamingCalibrator.step`` (host numpy in and out, the guarded
  step) and the UKF's guarded step of :func:`jaxcal.calibrate` on the same
  problem, jitted with the same per-row compile options
  (:func:`jaxcal.calibrators.programs.packed.jit_per_row`) and fed one row at a time the
  same way (host numpy in and out); median and 95th percentile microseconds per row;
* a fleet: ``StreamingCalibrator.run`` over ``units`` streams of ``rows`` rows and
  the UKF's fleet runner over the same arrays; microseconds per row;
* ``ops``: the kernels of both compiled stream steps (:func:`compiled_ops`).

The rows are the run's normalisation's mean plus 0.3 of its spread times Gaussian
draws (the costs of the any-model cases do not depend on the values), or rows a
caller gives :func:`bench_run` (``experiments/policy_turbofan.py``: the turbofan's
test rows). ``sync=true`` (the default) runs JAX's calls on the calling thread
(:func:`jaxcal.deploy.synchronous_dispatch`, as a deployed program should), both
methods alike; ``sync=false`` JAX's default thread-pool dispatch. Each result
records which (``synchronous``). Prints and writes JSON.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import sys
import time

import numpy as np


def _per_row(fns: dict, rows: int, block: int = 1) -> dict:
    """Each stream's cost per row, the streams' calls interleaved so that the
    machine's load falls on all of them alike (a shared, noisy machine): ``block``
    rows of one stream, then ``block`` of the next. Row by row (``block=1``) a
    large program's call also pays for the other's having evicted it from the
    CPU's caches: the turbofan's policy step cost about twice its cost in blocks of
    50 rows, which is closer to a deployed stream's (one program, row after row;
    results/bench/stream_profile.md, round 6)."""
    for fn in fns.values():
        fn(0)  # compiled
    times = {name: np.empty(rows - 1) for name in fns}
    for start in range(1, rows, block):
        for name, fn in fns.items():
            for t in range(start, min(start + block, rows)):
                tic = time.perf_counter()
                fn(t)
                times[name][t - 1] = time.perf_counter() - tic
    return {
        name: {
            "median_us": 1e6 * float(np.median(ts)),
            "p95_us": 1e6 * float(np.percentile(ts, 95)),
        }
        for name, ts in times.items()
    }


# what XLA's CPU runtime runs as no kernel of its own
_FREE_OPS = {"parameter", "constant", "tuple", "get-tuple-element", "bitcast"}


def _op_name(rhs: str) -> str:
    """The op of an HLO instruction's right-hand side ``shape op(operands)``, the
    shape maybe a tuple ``(f32[2], ...)``."""
    if rhs.startswith("("):  # skip the tuple shape to its closing parenthesis
        depth = 0
        for i, char in enumerate(rhs):
            depth += {"(": 1, ")": -1}.get(char, 0)
            if depth == 0:
                rhs = rhs[i + 1 :]
                break
    return rhs.split("(", 1)[0].split(" ")[-1]


def compiled_ops(compiled_text: str) -> dict:
    """The kernels (thunks) of a compiled program, from its optimised HLO text:
    ``entry`` ops of the main computation (each fusion, dot, copy, loop and branch
    one), and per ``while`` loop anywhere, its trip count and the ops of its body
    (run once per trip; ``every_call``: the loop is in the main computation, not in
    a branch, such as a stream's first-sample start, or another loop). On XLA's CPU
    runtime each kernel costs a microsecond or two whatever its size: for one small
    stream, their number is the step's cost."""
    bodies: dict[str, list[str]] = {}
    entry, current = "", None
    for line in compiled_text.splitlines():
        if line.endswith("{") and not line.startswith(" "):
            current = line.split(" ")[1 if line.startswith("ENTRY") else 0]
            current = current.lstrip("%")
            entry = current if line.startswith("ENTRY") else entry
            bodies[current] = []
        elif current and line.startswith("  ") and " = " in line:
            if _op_name(line.split(" = ", 1)[1]) not in _FREE_OPS:
                bodies[current].append(line)
    # the main path: the entry and what it calls inline (XLA's CPU "small calls")
    main, todo = set(), [entry]
    while todo:
        name = todo.pop()
        main.add(name)
        for line in bodies.get(name, []):
            if " call(" in line and "to_apply=%" in line:
                todo.append(line.split("to_apply=%", 1)[1].split(",", 1)[0])
    loops = []
    for name, lines in bodies.items():
        for line in lines:
            if " while(" not in line:
                continue
            body = line.split("body=%", 1)[1].split(",", 1)[0]
            trips = line.split('"known_trip_count":{"n":"', 1)
            trips = int(trips[1].split('"', 1)[0]) if len(trips) > 1 else None
            loops.append(
                {
                    "trips": trips,
                    "body_ops": len(bodies.get(body, [])),
                    "every_call": name in main,  # else in a branch or a loop
                }
            )
    calls = sum(len(bodies.get(name, [])) for name in main - {entry})
    return {"entry": len(bodies.get(entry, [])) + calls, "loops": loops}


def bench_run(
    run: str, rows: int, units: int, data: tuple | None = None, block: int = 1
) -> dict:
    """One run's costs (module docstring). ``data``: ``(w [units, rows, W], x [units,
    rows, S])`` rows to feed (the run's conditions and sensors, in their order)
    instead of the drawn ones: a model whose cost depends on the values (the
    turbofan's Newton solve converges in more or fewer iterations; a flagged row
    skips the model) is timed on its own data. ``block``: the one-stream calls
    interleaved in blocks of this many rows (:func:`_per_row`)."""
    import jax

    from jaxcal.calibrators.guard import guarded_update, initial_carry, sample_reason
    from jaxcal.calibrators.interface import run_fleet
    from jaxcal.calibrators.methods import config, make
    from jaxcal.calibrators.programs.packed import jit_per_row
    from jaxcal.deploy import StreamingCalibrator

    cal = StreamingCalibrator(run, trust_code=True)
    problem = cal.run_info.problem
    norm, rng = problem.norm, np.random.default_rng(0)
    shape = (units, rows)
    w = np.asarray(norm.w_mean) + 0.3 * np.asarray(norm.w_std) * rng.normal(
        size=(*shape, len(cal.conditions))
    )
    x = np.asarray(norm.x_mean) + 0.3 * np.asarray(norm.x_std) * rng.normal(
        size=(*shape, len(cal.sensors))
    )
    if data is not None:
        w, x = (np.asarray(a) for a in data)
        if w.shape[:2] != shape or x.shape[:2] != shape:
            raise ValueError(
                f"data: w {w.shape} and x {x.shape} must both start with (units, "
                f"rows) = {shape}"
            )
    w, x = w.astype(cal._dtype), x.astype(cal._dtype)
    out = {"run": run, "model": problem.model.name, "rows": rows, "units": units}
    out["block"] = block
    out["synchronous"] = cal.synchronous
    out["rows_from"] = "drawn" if data is None else "given"

    ukf = make(problem, config("ukf", {}))
    check = cal._check_dev

    # compiled as the policy's stream step is (the same options)
    @functools.partial(jit_per_row, warm_solve=cal._warm_solve)
    def ukf_step(carry, w_t, x_t):
        return guarded_update(ukf.step, carry, w_t, x_t, sample_reason(check, w_t, x_t))

    w0, x0 = jax.numpy.asarray(w[0, 0]), jax.numpy.asarray(x[0, 0])
    carry = [initial_carry(ukf.step, ukf.init(None, w0, x0), w0, x0)]

    def one(t):
        carry[0], res, reason = ukf_step(carry[0], w[0, t], x[0, t])
        jax.device_get((res.theta, reason))

    stream = cal._stream  # the policy's compiled stream step, as cal.step calls it
    row0 = np.concatenate([w[0, 0], x[0, 0]])
    out["ops"] = {
        "policy_stream": compiled_ops(
            stream._jitted.lower(stream._consts, cal._carry, row0).compile().as_text()
        ),
        "ukf_stream": compiled_ops(
            ukf_step.lower(carry[0], w[0, 0], x[0, 0]).compile().as_text()
        ),
    }
    streams = {"policy_stream": lambda t: cal.step(w[0, t], x[0, t]), "ukf_stream": one}
    out.update(_per_row(streams, rows, block))
    mask = np.ones(shape, bool)
    fleet_ukf = jax.jit(lambda w_, x_, m_: run_fleet(ukf, w_, x_, m_, check=check))
    fleets = {
        "policy_fleet_us_per_row": lambda: cal.run(w, x, mask),
        "ukf_fleet_us_per_row": lambda: jax.block_until_ready(fleet_ukf(w, x, mask)),
    }
    for fn in fleets.values():
        fn()  # compiled
    for name in fleets:
        out[name] = np.inf
    for _ in range(3):  # the best of three, interleaved
        for name, fn in fleets.items():
            tic = time.perf_counter()
            fn()
            spent = 1e6 * (time.perf_counter() - tic) / (units * rows)
            out[name] = min(out[name], spent)
    out["stream_ratio"] = (
        out["policy_stream"]["median_us"] / out["ukf_stream"]["median_us"]
    )
    out["fleet_ratio"] = out["policy_fleet_us_per_row"] / out["ukf_fleet_us_per_row"]
    return out


@dataclasses.dataclass(frozen=True)
class Options:
    """The script's ``key=value`` options (module docstring)."""

    runs: str = ""
    rows: int = 400
    units: int = 100
    sync: bool = True
    block: int = 1  # one-stream calls interleaved in blocks of this many rows
    out: str = ""


def main(argv: list[str]) -> int:
    from jaxcal.settings import parse_overrides

    try:
        opts = dataclasses.asdict(parse_overrides(argv, Options()))
        if not opts["runs"]:
            raise ValueError("runs=<run folder>[,...] is required")
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if opts["sync"]:
        from jaxcal.deploy import synchronous_dispatch

        synchronous_dispatch()  # before any JAX computation
    results = [
        bench_run(r, int(opts["rows"]), int(opts["units"]), block=int(opts["block"]))
        for r in opts["runs"].split(",")
    ]
    text = json.dumps(results, indent=1)
    print(text)
    if opts["out"]:
        os.makedirs(os.path.dirname(opts["out"]) or ".", exist_ok=True)
        with open(opts["out"], "w") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
