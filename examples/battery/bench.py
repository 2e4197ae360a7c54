"""Throughput of the joint UKF on the battery ECM: jaxcal's against dynamax's.

Both filters run the same ECM, settings and data (the first ``steps`` samples of
each unit; a fleet of ``fleet`` streams is the 4 units repeated), jitted, timed
after compilation (median of 3 runs), in one process:

* jaxcal: ``jaxcal.calibrate``'s UKF as built by ``build_calibrator`` and run by its
  jitted fleet runner (``lax.scan`` over time, ``vmap`` over the streams);
* dynamax: ``unscented_kalman_filter`` jitted, ``vmap`` over the streams for the
  fleet.

Samples/s = streams x steps / seconds; the ratio jaxcal / dynamax is reported.
"""

from __future__ import annotations

import time
import traceback

import numpy as np


def _median_seconds(fn, repeats: int = 3) -> float:
    import jax

    jax.block_until_ready(fn())  # compile
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def _streams(frame, num: int, steps: int):
    """A frame of ``num`` units: the data's units cycled, first ``steps`` rows."""
    import pandas as pd

    units = sorted(frame.unit.unique())
    parts = []
    for i in range(num):
        part = frame[frame.unit == units[i % len(units)]].iloc[:steps].copy()
        part["unit"] = i + 1
        parts.append(part)
    return pd.concat(parts, ignore_index=True)


def _jaxcal_seconds(sub) -> float:
    from jaxcal.calibrators import methods
    from jaxcal.data.buckets import bucket_units
    from jaxcal.data.readers import read_dataset
    from jaxcal.problem import Problem
    from model import MODEL
    from peers import THETA, UKF
    from run import _method_options

    cols = ["unit", "time", "current", "dt", "voltage"]  # the model's columns only
    data = read_dataset(sub[cols], MODEL).for_model(MODEL, None)
    problem = Problem.build(MODEL, data, theta=THETA, noise={"voltage": UKF["noise"]})
    buckets = bucket_units(data, np.float64)
    cfg = methods.config("ukf", _method_options("ukf", {}))
    built = methods.build(problem, cfg, buckets)
    return _median_seconds(lambda: built.run(buckets.parts[0]).theta)


def _dynamax_seconds(sub, num: int) -> float:
    import jax
    import jax.numpy as jnp

    from peers import make_dynamax_filter

    cols = [jnp.asarray(sub[c].to_numpy().reshape(num, -1)) for c in ("current", "dt", "voltage")]  # fmt: skip
    track = make_dynamax_filter()
    fn = jax.jit(track) if num == 1 else jax.jit(jax.vmap(track))
    args = [c[0] for c in cols] if num == 1 else cols
    return _median_seconds(lambda: fn(*args)[0])


def run_bench(frame, fleet: int, steps: int) -> dict:
    """``{"single": {...}, "fleet": {...}}`` with samples/s of each and the ratio."""
    out = {"steps": steps, "fleet_size": fleet}
    for label, num in (("single", 1), ("fleet", fleet)):
        sub = _streams(frame, num, steps)
        row = {"streams": num}
        for name, fn in (("jaxcal", lambda s=sub: _jaxcal_seconds(s)),
                         ("dynamax", lambda s=sub, n=num: _dynamax_seconds(s, n))):  # fmt: skip
            try:
                row[name] = num * steps / fn()
            except Exception as exc:  # report, keep the other peer's number
                traceback.print_exc()
                row[f"{name}_error"] = f"{type(exc).__name__}: {str(exc)[:300]}"
        if "jaxcal" in row and "dynamax" in row:
            row["ratio"] = row["jaxcal"] / row["dynamax"]
        print(f"  {label}: {row}", flush=True)
        out[label] = row
    return out
