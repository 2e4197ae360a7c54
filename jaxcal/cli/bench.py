"""``python -m jaxcal.bench engine``: engine throughput on this CPU, printed as JSON.

Measures, in one process: compile time of the jitted evaluate, single-call latency
at batch 1 (blocking, median of repeats = the real-time cost of one sample),
throughput at a large batch (default 65,536 operating points spread over the envelope
with random small health modifiers), the fraction converged, and the float precision
used. Options (``key=value``, or the flag spellings ``--engine agtf30``): ``engine=``
(``cmapss`` or ``agtf30``), ``batch=N``, ``repeats=K``, ``out=PATH`` (also write the
JSON).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from typing import Literal

import jax
import numpy as np

from jaxcal.cache import enable_compilation_cache
from jaxcal.cli.args import flags_as_overrides, parse_command_line
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.engine import load_engine
from jaxcal.precision import enable_x64, float_dtype
from jaxcal.runs.atomic import write_atomic
from jaxcal.settings import check_output_path, parse_overrides

USAGE = (
    "usage: python -m jaxcal.bench engine [engine=cmapss|agtf30] [batch=N] "
    "[repeats=K] [out=PATH]  (or --engine X --batch N --repeats K --out PATH)"
)
FLAGS = {f"--{k}": k for k in ("engine", "batch", "repeats", "out")}


@dataclasses.dataclass(frozen=True)
class BenchArgs:
    """What ``python -m jaxcal.bench engine`` measures and where it writes."""

    engine: Literal["cmapss", "agtf30"] = "cmapss"
    batch: int = 65536  # operating points of the throughput call
    repeats: int = 5  # timed calls, the median reported
    out: str | None = None  # also write the JSON here

    def __post_init__(self) -> None:
        if self.batch < 1 or self.repeats < 1:
            raise ValueError(
                f"batch and repeats must be positive integers, got {self.batch}, "
                f"{self.repeats}"
            )


def parse_args(argv: list[str]) -> BenchArgs:
    """The :class:`BenchArgs` of a command line (``engine`` first: what to bench).

    Raises:
        ValueError: no ``engine``, or a bad key, flag or value (named).
    """
    if not argv or argv[0] != "engine":
        raise ValueError("say what to bench: engine")
    args = parse_overrides(flags_as_overrides(argv[1:], FLAGS), BenchArgs())
    if args.out is not None:  # refused now, not after the benchmark
        check_output_path(args.out, "out")
    return args


def envelope_points(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n operating points over alt 0-42 kft, Mach 0-0.85, TRA 20-100, ISA -30/+40 degR,
    with health modifiers uniform in [-0.03, 0]."""
    rng = np.random.default_rng(seed)
    alt = rng.uniform(0.0, 42000.0, n)
    mach = rng.uniform(0.0, 0.85, n)
    t2 = np.asarray(isa_total_temperature(alt, mach)) + rng.uniform(-30.0, 40.0, n)
    w = np.stack([alt, mach, rng.uniform(20.0, 100.0, n), t2], 1)
    return w, rng.uniform(-0.03, 0.0, (n, 10))


def _timed(fn, *args, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        out.append(time.perf_counter() - t0)
    return out


def bench_engine(name: str, batch: int, repeats: int) -> dict:
    engine = load_engine(name)
    f = jax.jit(engine.evaluate)
    w1, th1 = envelope_points(1, seed=1)
    t0 = time.perf_counter()
    compiled1 = f.lower(w1, th1).compile()
    compile_1 = time.perf_counter() - t0
    jax.block_until_ready(compiled1(w1, th1))
    lat = _timed(compiled1, w1, th1, repeats=max(repeats, 50))
    wb, thb = envelope_points(batch)
    t0 = time.perf_counter()
    compiled_b = f.lower(wb, thb).compile()
    compile_b = time.perf_counter() - t0
    x, info = compiled_b(wb, thb)
    jax.block_until_ready(x)
    tb = _timed(compiled_b, wb, thb, repeats=repeats)
    return {
        "benchmark": "engine",
        "engine": name,
        "float_precision": str(float_dtype()),
        "devices": [str(d) for d in jax.devices()],
        "cpu_count": os.cpu_count(),
        "compile_seconds": {"batch_1": compile_1, f"batch_{batch}": compile_b},
        "batch_1": {
            "latency_ms_median": 1e3 * float(np.median(lat)),
            "latency_ms_min": 1e3 * float(np.min(lat)),
            "solves_per_s": 1.0 / float(np.median(lat)),
        },
        f"batch_{batch}": {
            "seconds_median": float(np.median(tb)),
            "seconds_min": float(np.min(tb)),
            "solves_per_s": batch / float(np.median(tb)),
            "solves_per_s_best": batch / float(np.min(tb)),
        },
        "fraction_converged": float(np.mean(np.asarray(info.converged))),
        "newton_iterations": {
            "mean": float(np.mean(np.asarray(info.iterations))),
            "max": int(np.max(np.asarray(info.iterations))),
        },
    }


def main(argv=None) -> int:
    args, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if args is None:
        return code
    enable_x64()
    enable_compilation_cache()
    result = bench_engine(args.engine, args.batch, args.repeats)
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        write_atomic(args.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
