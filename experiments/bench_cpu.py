"""CPU throughput of jaxcal against its peers, measured in one run, as one JSON doc.

Sections (each in :mod:`cpubench`): policy inference (vs numpy and the matmul
roofline), RL training (our jitted CLAC/SAC vs SBX's SAC), the engine model (single vs
batched solves), the UKF (vs filterpy and dynamax, one unit and a fleet, on the engine
and on a toy model) and end to end (the training job's wall time and accuracy, the
deployed calibrator's cost per sample, against the paper's published numbers).

Every figure is ``{"value", "best", "unit", "better", "peer", "ratio", ...}`` with
``ratio > 1`` meaning jaxcal is better (faster); a figure whose peer has no number
says why in ``reason``. Optional peers come from ``pip install -e '.[bench]'`` (after
``torch==2.13.0``); when one is missing the figure says so instead of failing.

Usage::

    python experiments/bench_cpu.py [--quick] [--out PATH] [--train] [--final PATH]
        [--no-optional-peers] [--sections policy,training,engine,ukf,end_to_end]

The document is printed on stdout and written atomically to ``--out`` (default
``results/bench/bench_cpu.json``; with ``--quick`` nothing is written unless ``--out``
is given). Progress goes to stderr.
"""

from __future__ import annotations

import os

# Thread pins must precede the numpy import: numpy's BLAS reads them once.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import argparse  # noqa: E402
import datetime  # noqa: E402
import importlib.metadata  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
from cpubench.end_to_end import TRAIN_COMMAND, bench_end_to_end, run_training_job  # noqa: E402
from cpubench.engine import bench_engine_section  # noqa: E402
from cpubench.measure import IMPORT_SIDE_EFFECTS, CpuWatch, skipped, x64  # noqa: E402
from cpubench.policy import bench_policy  # noqa: E402
from cpubench.training import QUICK_SIZES, TrainingSizes, bench_training  # noqa: E402
from cpubench.ukf import bench_ukf  # noqa: E402

from jaxcal.cache import enable_compilation_cache  # noqa: E402
from jaxcal.runs.folder import write_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = ("policy", "training", "engine", "ukf", "end_to_end")
DEFAULT_OUT = "results/bench/bench_cpu.json"
RATIO_CONVENTION = (
    "ratio = our rate / peer rate = peer time / our time (medians); > 1 means jaxcal "
    "is faster. ratio_best uses each side's fastest repeat. For the roofline figure "
    "the ratio is the fraction of the roofline reached."
)
PACKAGES = ("jax", "jaxlib", "flax", "optax", "numpy", "torch", "sbx-rl",
            "stable_baselines3", "filterpy", "dynamax", "gymnasium")  # fmt: skip


def _log(message: str) -> None:
    print(f"[bench_cpu] {message}", file=sys.stderr, flush=True)


def machine_info() -> dict:
    """CPU, thread pins and package versions (``None`` for absent packages)."""
    model = None
    try:
        with open("/proc/cpuinfo") as fh:
            model = next((ln.split(":", 1)[1].strip() for ln in fh
                          if ln.startswith("model name")), None)  # fmt: skip
    except OSError:
        pass
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "cpu_model": model,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax_devices": [str(d) for d in jax.devices()],
        "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
        "torch_threads": "1 (torch.set_num_threads in the training section)",
        "versions": versions,
    }


def run_sections(args: argparse.Namespace) -> dict:
    """Runs the chosen sections in order; returns ``{name: section dict}``."""
    quick, peers = args.quick, not args.no_optional_peers
    chosen = args.sections
    out: dict[str, dict] = {}

    def run(name: str, fn, *, use_x64: bool) -> None:
        if name not in chosen:
            return
        _log(f"section {name} ...")
        watch = CpuWatch()
        with x64(use_x64):
            result = fn()
        result["machine"] = watch.report()
        _log(f"section {name} done in {result['machine']['seconds']:.0f} s")
        out[name] = result

    run("policy", lambda: bench_policy(
        batch=256 if quick else 4096, single_calls=20 if quick else 200,
        repeats=2 if quick else 15, matmul_n=128 if quick else 2048, child=not quick,
    ), use_x64=False)  # fmt: skip
    run("training", lambda: bench_training(
        QUICK_SIZES if quick else TrainingSizes(), peers=peers, like_for_like=not quick
    ), use_x64=False)  # fmt: skip
    if quick:
        run("engine", lambda: {"config": {}, "figures": {
            name: skipped("--quick: the engine's Newton solve takes ~35 s to compile")
            for name in ("single_call", "batched")}}, use_x64=True)  # fmt: skip
    else:
        # Before the UKF: filterpy's engine call reuses this section's batch-1 program.
        run("engine", lambda: bench_engine_section(batch=16384, repeats=5),
            use_x64=True)  # fmt: skip
    run("ukf", lambda: bench_ukf(quick=quick, peers=peers), use_x64=True)

    ukf_us = None
    engine_fig = out.get("ukf", {}).get("figures", {}).get("engine_single_vs_filterpy")
    if engine_fig is not None:
        ukf_us = engine_fig["value"]
    final = args.final
    if args.train and "end_to_end" in chosen:
        _log(f"running the training job ({TRAIN_COMMAND}), about 12 minutes ...")
        final = run_training_job(ROOT)
    run("end_to_end", lambda: bench_end_to_end(
        ROOT, quick=quick, run_final=final, ukf_engine_us=ukf_us
    ), use_x64=False)  # fmt: skip
    return out


def summary(sections: dict) -> dict:
    """``"section.figure" -> ratio`` (``None`` where the figure has a reason)."""
    return {
        f"{name}.{key}": fig.get("ratio")
        for name, section in sections.items()
        for key, fig in section.get("figures", {}).items()
    }


def _finite(tree):
    """The document with non-finite floats as ``None`` (strict JSON has no NaN)."""
    if isinstance(tree, dict):
        return {k: _finite(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [_finite(v) for v in tree]
    if isinstance(tree, float) and not math.isfinite(tree):
        return None
    return tree


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line (see the module docstring)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="tiny sizes, no engine")
    p.add_argument("--out", default=None, help=f"JSON path (default {DEFAULT_OUT})")
    p.add_argument("--train", action="store_true", help=f"run `{TRAIN_COMMAND}` first")
    p.add_argument("--final", default=None, help="final.json of a training run to read")
    p.add_argument("--no-optional-peers", action="store_true",
                   help="skip sbx, filterpy and dynamax even if installed")  # fmt: skip
    p.add_argument("--sections", default=",".join(SECTIONS))
    args = p.parse_args(argv)
    args.sections = tuple(s.strip() for s in args.sections.split(",") if s.strip())
    unknown = set(args.sections) - set(SECTIONS)
    if unknown:
        p.error(f"unknown section(s) {sorted(unknown)}; choose from {SECTIONS}")
    if args.out is None and not args.quick:
        args.out = str(ROOT / DEFAULT_OUT)
    return args


def main(argv: list[str] | None = None) -> int:
    """Runs the benchmark, prints the JSON document and writes it to ``--out``."""
    args = parse_args(argv)
    enable_compilation_cache()  # engine programs compile in ~35 s; reruns reuse them
    start = time.perf_counter()
    started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    sections = run_sections(args)
    doc = {
        "benchmark": "jaxcal CPU throughput against peers",
        "command": "python experiments/bench_cpu.py " + " ".join(sys.argv[1:]),
        "make_target": "make bench",
        "quick": args.quick,
        "optional_peers": not args.no_optional_peers,
        "started_utc": started,
        "total_seconds": time.perf_counter() - start,
        "ratio_convention": RATIO_CONVENTION,
        "machine": machine_info(),
        "peer_import_side_effects": IMPORT_SIDE_EFFECTS,
        "summary_ratios": summary(sections),
        "sections": sections,
    }
    text = json.dumps(_finite(doc), indent=1, allow_nan=False)
    print(text)
    if args.out:
        write_atomic(Path(args.out), text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
