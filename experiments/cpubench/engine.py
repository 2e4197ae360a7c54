"""Engine model throughput, through :func:`jaxcal.bench.bench_engine` (not duplicated).

Figures: solves/s of one jitted call per sample (batch 1, blocking) and of one call
over a large batch of envelope points. No other open turbofan model is installed here
to compare with (pyCycle is not among the bench extras), so the single-call figure has
no peer; the batched figure's peer is the single-call rate, i.e. the ratio is what
batching (``vmap`` inside one call) gains over a loop of single calls.
"""

from __future__ import annotations

from cpubench.measure import figure, missing_peer, peer
from jaxcal.cli.bench import bench_engine


def bench_engine_section(*, batch: int, repeats: int) -> dict:
    """Runs ``jaxcal.bench.bench_engine("cmapss", batch, repeats)`` and reports it."""
    raw = bench_engine("cmapss", batch, repeats)
    single = raw["batch_1"]
    batched = raw[f"batch_{batch}"]
    single_rate = single["solves_per_s"]
    single_best = 1e3 / single["latency_ms_min"]
    return {
        "config": {
            "engine": "cmapss",
            "batch": batch,
            "repeats": repeats,
            "float_precision": raw["float_precision"],
            "compile_seconds": raw["compile_seconds"],
            "fraction_converged": raw["fraction_converged"],
            "newton_iterations": raw["newton_iterations"],
        },
        "figures": {
            "single_call": figure(
                single_rate,
                "solves/s",
                "higher",
                missing_peer(
                    "another engine model",
                    "no comparable open engine model installed (pyCycle is not a "
                    "bench extra)",
                ),
                best=single_best,
                latency_ms=single["latency_ms_median"],
            ),
            "batched": figure(
                batched["solves_per_s"],
                "solves/s",
                "higher",
                peer(
                    "loop of single jitted calls", single_rate, "solves/s", single_best
                ),
                best=batched["solves_per_s_best"],
                batch=batch,
            ),
        },
    }
