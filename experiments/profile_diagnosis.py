"""Where a diagnosis spends its time: the stages, the hot functions, the memory.

Runs one diagnosis (``python -m jaxcal.diagnose``'s pipeline) on a NASA C-MAPSS text
file restricted to its first ``units`` units, or on a synthetic turbofan fleet of
``units`` units (the loop study's record, :mod:`jaxcal.models.turbofan.scenario`,
noise levels known), and prints one JSON object: rows, units, the verdict, wall and
CPU seconds, peak resident memory, the seconds of each stage (``timings``, as in
``report.json``) and, with ``profile=true``, the functions with the most own time
and the cumulative time of the diagnosis's hot spots (cProfile; the model's
compiled programs count where the host waits for them: ``numpy.asarray``).

Usage::

    python experiments/profile_diagnosis.py [data=FD001|synthetic|<path.txt>]
        [units=10] [profile=true] [top=20] [kind=sensor_bias] [seed=0]
        [rows_per_cycle=2] [cycle_stride=1] [out=<file.json>]

``results/loop/profile.md`` reads its output (before and after issue 43).
"""

from __future__ import annotations

import cProfile
import dataclasses
import json
import os
import pstats
import resource
import sys
import time

from jaxcal.settings import parse_overrides

DATA_DIR = os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data", "cmapss"
)
# functions whose cumulative time tells the stages' costs apart (name: file:function)
HOT = {
    "model evaluation (linearize / simulate)": ("signatures.py", "signatures"),
    "fit_model": ("fitting.py", "fit_model"),
    "identify": ("identify.py", "identify"),
    "screen steps": ("screen.py", "_step"),
    "noise: projection_bias": ("noise_fit.py", "projection_bias"),
    "noise: nn_scale": ("noise_fit.py", "nn_scale"),
    "fallback": ("fallback.py", "fallback"),
    "discrepancy fit": ("discrepancy.py", "fit_discrepancy"),
    "jax trace (jit cache miss)": ("pjit.py", "cache_miss"),
    "host waits for JAX (numpy.asarray)": ("~", "<built-in method numpy.asarray>"),
}


@dataclasses.dataclass(frozen=True)
class ProfileConfig:
    data: str = "FD001"  # FD00x (train file in the shared data), a .txt path, synthetic
    units: int = 10  # the first units of the file / the synthetic fleet's size
    profile: bool = True  # cProfile the run (slower by ~10 %)
    top: int = 20  # functions listed by own time
    kind: str = "sensor_bias"  # the synthetic fleet's effect (loop_study kinds)
    seed: int = 0
    rows_per_cycle: int = 2  # synthetic: samples kept per flight
    cycle_stride: int = 1  # synthetic: keep every k-th cycle
    out: str = ""  # also write the JSON here


def _load(cfg: ProfileConfig, model):
    """``(dataset, declared, units, noise_std)`` of the run."""
    if cfg.data == "synthetic":
        import jax

        from jaxcal.diagnosis.data.synthetic import make_synthetic_data
        from jaxcal.models.turbofan.scenario import ScenarioConfig, make_scenario

        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from loop_study import KINDS, synthetic_config

        declared = ("HPT_eff_mod",)
        scenario = make_scenario(
            ScenarioConfig(
                num_units=cfg.units, rows_per_cycle=cfg.rows_per_cycle,
                cycle_stride=cfg.cycle_stride, declared=declared,
            )
        )  # fmt: skip
        key = jax.random.fold_in(
            jax.random.fold_in(jax.random.key(cfg.seed), KINDS.index(cfg.kind)), 0
        )
        syn = make_synthetic_data(
            key, model, cfg.kind, synthetic_config(declared), scenario
        )
        return syn.data, declared, None, syn.noise_std
    from jaxcal.data.readers import read_dataset

    path = cfg.data if cfg.data.endswith(".txt") else os.path.join(
        DATA_DIR, f"train_{cfg.data}.txt"
    )  # fmt: skip
    data = read_dataset(os.path.normpath(path), model)
    units = sorted(set(data.unit.tolist()))[: cfg.units]
    return data, ("HPC_eff_mod", "HPC_flow_mod"), units, None


def _hot(stats: pstats.Stats) -> dict:
    out = {}
    for label, (file, func) in HOT.items():
        total = 0.0
        for (path, _line, name), (_cc, _nc, _tt, ct, _callers) in stats.stats.items():
            if name == func and (file == "~" or path.endswith(file)):
                total = max(total, ct)  # the outermost call (recursion counted once)
        out[label] = round(total, 2)
    return out


def _top(stats: pstats.Stats, top: int) -> list[dict]:
    rows = sorted(stats.stats.items(), key=lambda kv: -kv[1][2])[:top]
    return [
        {
            "function": f"{os.path.basename(path)}:{line}({name})",
            "calls": nc,
            "own_s": round(tt, 2),
            "cumulative_s": round(ct, 2),
        }
        for (path, line, name), (_cc, nc, tt, ct, _callers) in rows
    ]


def main(argv: list[str]) -> int:
    try:
        cfg = parse_overrides(argv, ProfileConfig())
    except ValueError as err:
        print(f"profile_diagnosis: {err}", file=sys.stderr)
        return 2
    from jaxcal.cache import enable_compilation_cache, map_large_arrays
    from jaxcal.diagnosis.pipeline import LoopConfig, diagnose
    from jaxcal.models import load
    from jaxcal.precision import enable_x64

    enable_x64()
    enable_compilation_cache()
    map_large_arrays()  # as the command line
    model = load("cmapss")
    data, declared, units, noise_std = _load(cfg, model)
    prof = cProfile.Profile() if cfg.profile else None
    cpu0, wall0 = time.process_time(), time.perf_counter()
    if prof is not None:
        prof.enable()
    res = diagnose(data, model, declared, LoopConfig(), units=units,
                   noise_std=noise_std, progress=True)  # fmt: skip
    if prof is not None:
        prof.disable()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    out = {
        "data": cfg.data,
        "units": res.data.num_units,
        "rows": res.data.num_rows,
        "verdict": res.verdict,
        "added": list(res.added),
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "timings": res.timings,
        "config": dataclasses.asdict(cfg),
    }
    if prof is not None:
        stats = pstats.Stats(prof)
        out["hot_cumulative_s"] = _hot(stats)
        out["top_own_time"] = _top(stats, cfg.top)
    emit(out, cfg.out)
    return 0


def emit(out: dict, path: str) -> None:
    """Print ``out`` as JSON, and write it to ``path`` too when one is given."""
    text = json.dumps(out, indent=1)
    if path:
        from jaxcal.diagnosis.report.write import write_text

        write_text(path, text + "\n")
    print(text)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
