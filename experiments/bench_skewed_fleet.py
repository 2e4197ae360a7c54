"""Peak memory and time of ``jaxcal.calibrate`` on a skewed fleet (issue 25, memory).

One long unit beside many one-row units: padding every unit to the longest asks for
``units x longest`` cells; bucketing by length keeps the cells close to the rows.
Each case runs in a fresh process (peak RSS is per process)::

    PYTHONPATH=. JAX_PLATFORMS=cpu python experiments/bench_skewed_fleet.py \
        20000 100000 --short 2000 --method ukf

prints one line per case: long length, short units, seconds, peak RSS (GB) or the
error. Not a test (wall-clock and memory depend on the machine).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def tank(w, theta):
    import jax.numpy as jnp

    heat, inflow = w[0], w[1]
    leak, loss = theta[0], theta[1]
    level = inflow / leak
    temp = 20.0 + heat / (inflow * (1.0 + loss))
    return jnp.stack([level, temp, leak * level * (1.0 - 0.1 * loss)])


def frame(long: int, short: int, seed: int = 0):
    import jax
    import numpy as np
    import pandas as pd

    rng = np.random.default_rng(seed)
    n = long + short
    unit = np.concatenate([np.zeros(long, np.int64), 1 + np.arange(short)])
    time_ = np.concatenate([np.arange(long), np.zeros(short)])
    w = np.stack([rng.uniform(5, 30, n), rng.uniform(0.5, 2.0, n)], 1)
    theta = np.stack([np.full(n, 1.2), np.full(n, 0.2)], 1)
    x = np.asarray(jax.vmap(tank)(w, theta)) + 0.02 * rng.standard_normal((n, 3))
    cols = {"heat": w[:, 0], "inflow": w[:, 1], "unit": unit, "time": time_}
    cols.update({k: x[:, j] for j, k in enumerate(("level", "temp", "outflow"))})
    return pd.DataFrame(cols)


def one_case(long: int, short: int, method: str) -> dict:
    import jaxcal

    model = jaxcal.Model.from_function(
        tank,
        conditions={"heat": "kW", "inflow": "kg/s"},
        parameters={"leak": (1.0, 0.5, 2.0), "loss": (0.1, 0.0, 0.5)},
        outputs={"level": "m", "temp": "degC", "outflow": "kg/s"},
        condition_range=([0.0, 0.1], [50.0, 5.0]),
        name="tank",
    )
    data = frame(long, short)
    start = time.perf_counter()
    try:
        result = jaxcal.calibrate(model, data, method=method)
        outcome = f"ok, {int(result.valid.sum())} valid rows"
    except MemoryError as err:
        outcome = f"MemoryError: {err}"
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # kB -> GB
    return {"long": long, "short": short, "seconds": round(seconds, 1),
            "peak_gb": round(peak, 2), "outcome": outcome}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("long", type=int, nargs="+", help="rows of the long unit")
    parser.add_argument("--short", type=int, default=2000, help="one-row units")
    parser.add_argument("--method", default="ukf")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(one_case(args.long[0], args.short, args.method)))
        return
    for long in args.long:
        cmd = [sys.executable, __file__, str(long), "--short", str(args.short),
               "--method", args.method, "--child"]  # fmt: skip
        proc = subprocess.run(cmd, capture_output=True, text=True)
        line = proc.stdout.strip().splitlines()[-1:] or [proc.stderr.strip()[-300:]]
        print(line[0], flush=True)


if __name__ == "__main__":
    main()
