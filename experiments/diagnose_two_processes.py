"""A synthetic turbofan fleet diagnosed on one process, then on several
``jax.distributed`` processes of this machine (issue 43 item 2): the same report, and
the wall time of each.

Usage::

    python experiments/diagnose_two_processes.py [units=1000] [processes=2]
        [kind=sensor_bias] [seed=0] [pin=false]
        [out=results/loop/scaling/two_processes.json]

1. The fleet of ``profile_diagnosis.py data=synthetic`` (the loop study's record,
   noise levels known) is made once, in a child process, and kept in a temporary
   folder: made in every process, its generation alone took 10.9 GB at 1,000 units.
2. One process diagnoses it; then (after it, not beside it) ``processes`` processes
   joined on localhost (:func:`jaxcal.fleet.distributed.initialize`), which split the
   model's evaluations by units (:mod:`jaxcal.diagnosis.data.sharding`). Each process
   writes its report (``report.json``'s content without the stage seconds). With
   ``pin=true`` process ``i`` runs on core ``i`` alone (the one process on core 0):
   the machine as one-core hosts.
3. Prints one JSON object: per run the wall seconds from the start of the processes
   to the last one's exit (``wall_s``: imports, programs and data loaded included)
   and of the diagnosis alone in each process, peak resident memory, the machine's
   load average before and after, the verdict; and whether every process's report
   equals the one-process report (``same_report``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import resource
import socket
import subprocess
import sys
import tempfile
import time

from jaxcal.settings import parse_overrides

HERE = os.path.dirname(os.path.abspath(__file__))


@dataclasses.dataclass(frozen=True)
class TwoProcessConfig:
    units: int = 1000  # the synthetic fleet's engines
    processes: int = 2  # processes of the cluster run (after the one-process run)
    kind: str = "sensor_bias"  # the fleet's effect (loop_study kinds)
    seed: int = 0
    timeout_s: int = 3600  # per run
    # each process on its own core (process i on core i, the one process on core 0):
    # the machine as one-core hosts (Linux), instead of every process on every core
    pin: bool = False
    out: str = ""  # also write the JSON here


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def generate(cfg_json: str, path: str) -> None:
    """Child: make the fleet as ``profile_diagnosis.py`` does and pickle it."""
    sys.path.insert(0, HERE)
    from profile_diagnosis import ProfileConfig, _load

    from jaxcal.cache import enable_compilation_cache
    from jaxcal.models import load
    from jaxcal.precision import enable_x64

    cfg = TwoProcessConfig(**json.loads(cfg_json))
    enable_x64()
    enable_compilation_cache()
    prof = ProfileConfig(data="synthetic", units=cfg.units, kind=cfg.kind,
                         seed=cfg.seed, profile=False)  # fmt: skip
    with open(path, "wb") as f:
        pickle.dump(_load(prof, load("cmapss")), f)


def worker(
    data_path: str, out_dir: str, port: str, num: int, index: int, pin: bool
) -> None:
    """Child: one process of a run; writes ``process<index>.json``."""
    if pin:
        os.sched_setaffinity(0, {index % os.cpu_count()})
    from jaxcal.fleet.distributed import initialize

    initialize(f"127.0.0.1:{port}", num, index, timeout_s=600)
    from jaxcal.cache import enable_compilation_cache
    from jaxcal.diagnosis.pipeline import LoopConfig, diagnose
    from jaxcal.diagnosis.report.write import report_dict
    from jaxcal.models import load
    from jaxcal.precision import enable_x64

    enable_x64()
    enable_compilation_cache()
    model = load("cmapss")
    with open(data_path, "rb") as f:
        data, declared, units, noise_std = pickle.load(f)
    start = time.perf_counter()
    res = diagnose(data, model, declared, LoopConfig(), units=units,
                   noise_std=noise_std, progress=index == 0)  # fmt: skip
    wall = time.perf_counter() - start
    rep = report_dict(res)
    timings = rep.pop("timings")
    summary = {
        "diagnosis_s": round(wall, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "timings": timings,
    }
    with open(os.path.join(out_dir, f"process{index}.json"), "w") as f:
        json.dump({"report": rep, "summary": summary}, f)


def _run(commands: list[list[str]], timeout_s: int) -> float:
    """Start the processes together, wait for all; their wall seconds."""
    start = time.perf_counter()
    procs = [subprocess.Popen(cmd) for cmd in commands]
    try:
        codes = [proc.wait(timeout=timeout_s) for proc in procs]
    except subprocess.TimeoutExpired:
        for proc in procs:
            proc.kill()
        raise RuntimeError(f"a process ran past {timeout_s} s") from None
    if any(codes):
        raise RuntimeError(f"a process failed: exit codes {codes}")
    return time.perf_counter() - start


def _cluster_run(cfg, data_path: str, tmp: str, num: int) -> tuple[dict, list]:
    out_dir = os.path.join(tmp, f"run{num}")
    os.makedirs(out_dir)
    port = str(_free_port())
    commands = [
        [
            sys.executable,
            __file__,
            "worker",
            data_path,
            out_dir,
            port,
            str(num),
            str(i),
            str(int(cfg.pin)),
        ]
        for i in range(num)
    ]
    load_before = os.getloadavg()
    wall = _run(commands, cfg.timeout_s)
    load_after = os.getloadavg()
    got = []
    for i in range(num):
        with open(os.path.join(out_dir, f"process{i}.json")) as f:
            got.append(json.load(f))
    run = {
        "processes": num,
        "wall_s": round(wall, 1),
        "diagnosis_s": [g["summary"]["diagnosis_s"] for g in got],
        "peak_rss_mb": [g["summary"]["peak_rss_mb"] for g in got],
        "timings_process0": got[0]["summary"]["timings"],
        "load_average_before": [round(v, 2) for v in load_before],
        "load_average_after": [round(v, 2) for v in load_after],
        "verdict": got[0]["report"]["verdict"],
        "added": got[0]["report"]["added"],
    }
    return run, [g["report"] for g in got]


def main(argv: list[str]) -> int:
    try:
        cfg = parse_overrides(argv, TwoProcessConfig())
        if cfg.processes < 2 or cfg.units < 1:
            raise ValueError("need processes >= 2 and units >= 1")
    except ValueError as err:
        print(f"diagnose_two_processes: {err}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="jaxcal_two_processes_") as tmp:
        data_path = os.path.join(tmp, "fleet.pkl")
        start = time.perf_counter()
        code = subprocess.call(
            [sys.executable, __file__, "generate",
             json.dumps(dataclasses.asdict(cfg)), data_path]
        )  # fmt: skip
        if code:
            print(
                f"diagnose_two_processes: generation failed ({code})", file=sys.stderr
            )
            return 1
        generation_s = time.perf_counter() - start
        one, (one_report,) = _cluster_run(cfg, data_path, tmp, 1)
        many, reports = _cluster_run(cfg, data_path, tmp, cfg.processes)
    out = {
        "units": one_report["data"]["units"],
        "rows": one_report["data"]["rows"],
        "generation_s": round(generation_s, 1),
        "runs": [one, many],
        "same_verdict": many["verdict"] == one["verdict"],
        # every process's report, the stage seconds left out, equals one process's
        "same_report": all(r == one_report for r in reports),
        "wall_ratio": round(many["wall_s"] / one["wall_s"], 3),
        "config": dataclasses.asdict(cfg),
    }
    from profile_diagnosis import emit

    emit(out, cfg.out)
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["generate"]:
        generate(*sys.argv[2:4])
    elif sys.argv[1:2] == ["worker"]:
        path, out_dir, port, num, index, pin = sys.argv[2:8]
        worker(path, out_dir, port, int(num), int(index), pin == "1")
    else:
        raise SystemExit(main(sys.argv[1:]))
