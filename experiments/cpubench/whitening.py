"""The diagnosis's prewhitening on a fleet's arrays: the library's chunked form against
the table-wide form it replaced (one pass of the whole array per AR lag over an
``[N, S, order + 1]`` table), interleaved in one process; prints one JSON object.

The arrays have NASA FD002's shape (260 units of 128-378 rows, 9 outputs) and AR
orders 0-3: a residual ``[N, S]`` and candidate columns ``[N, S, C]``. Both forms give
the same bits (checked here on every array, and by
``tests/diagnosis/test_noise_model.py``).

Usage::

    python experiments/cpubench/whitening.py [repeats=7] [columns=1,10,30]
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import time

import numpy as np

from jaxcal.diagnosis.residuals.noise import MAX_ORDER, NoiseModel, positions
from jaxcal.settings import parse_overrides


def table_wide(model: NoiseModel, arr, position):
    """The whitening before the chunked form: a pass of the whole array per lag."""
    scale = model.sigma * np.sqrt(model.inflation)
    extra = (1,) * (arr.ndim - 2)
    table = model.filter_table(position)
    out = table[:, :, 0].reshape(table.shape[:2] + extra) * arr
    for k in range(1, MAX_ORDER + 1):
        coef = table[k:, :, k].reshape((arr.shape[0] - k, arr.shape[1]) + extra)
        if np.any(coef):
            out[k:] += coef * arr[:-k]
    return out / scale.reshape((1, -1) + extra)


@dataclasses.dataclass(frozen=True)
class Options:
    repeats: int = 7
    columns: str = "1,10,30"  # columns per output of each case (1: a residual)


def main(argv) -> dict:
    opts = parse_overrides(argv, Options())
    rng = np.random.default_rng(0)
    lengths = rng.integers(128, 379, 260)
    position = positions(np.r_[0, np.cumsum(lengths)], int(lengths.sum()))
    order = np.array([1, 2, 3, 0, 1, 2, 3, 1, 2])
    ar = np.zeros((order.size, MAX_ORDER))
    for s, p in enumerate(order):
        ar[s, :p] = rng.uniform(-0.3, 0.5, p) / max(p, 1)
    model = NoiseModel(rng.uniform(0.5, 2.0, order.size), ar, order,
                       np.ones(order.size), "estimated",
                       np.full(order.size, np.nan))  # fmt: skip
    out = {"rows": int(position.size), "outputs": int(order.size), "cases": []}
    for c in (int(v) for v in opts.columns.split(",")):
        shape = (position.size, order.size) + ((c,) if c > 1 else ())
        arr = rng.normal(size=shape)
        same = bool(np.array_equal(model.whiten(arr, position),
                                   table_wide(model, arr, position)))  # fmt: skip
        times = {"chunked": [], "table_wide": []}
        for _ in range(opts.repeats):  # interleaved: the machine is shared
            for name, fn in (("chunked", model.whiten), ("table_wide", table_wide)):
                start = time.perf_counter()
                fn(*((arr, position) if name == "chunked" else (model, arr, position)))
                times[name].append(time.perf_counter() - start)
        med = {k: statistics.median(v) for k, v in times.items()}
        out["cases"].append({
            "shape": list(shape), "same_bits": same,
            "chunked_ms": 1e3 * med["chunked"],
            "table_wide_ms": 1e3 * med["table_wide"],
            "speedup": med["table_wide"] / med["chunked"],
        })  # fmt: skip
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1:]), indent=1))
