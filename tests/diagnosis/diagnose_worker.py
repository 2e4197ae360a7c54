"""Subprocess side of the two-process diagnosis test (not a test module).

A diagnosis on two ``jax.distributed`` processes needs fresh interpreters (the
cluster is joined before any JAX computation), so ``test_two_processes.py`` runs

    python diagnose_worker.py stateful OUT_DIR PORT PROCESS_ID

in two of them: each diagnoses the same small fleet of a model with memory and writes
its report (:func:`report`) to ``OUT_DIR/process<i>.json``; the test compares both
with the same diagnosis in one process.
"""

from __future__ import annotations

import json
import os
import sys

# run as a script: make this folder's test modules importable
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def report() -> dict:
    """The report of the memory model's diagnosis (``test_diagnose_stateful``'s wall:
    three units, a bias on the load), without its wall seconds."""
    from test_diagnose_stateful import MODEL, NOISE, _dataset

    from jaxcal.diagnosis.pipeline import diagnose
    from jaxcal.diagnosis.report.write import report_dict

    result = diagnose(_dataset(bias=0.01), MODEL, ("R",), noise_std=NOISE)
    rep = report_dict(result)
    rep.pop("timings")
    return rep


def main(out_dir: str, port: str, process_id: int) -> None:
    from jaxcal.fleet.distributed import initialize

    initialize(f"127.0.0.1:{port}", 2, process_id, timeout_s=60)
    from jaxcal.cache import enable_compilation_cache
    from jaxcal.precision import enable_x64

    enable_x64()
    enable_compilation_cache()
    text = json.dumps(report(), indent=1)
    with open(os.path.join(out_dir, f"process{process_id}.json"), "w") as f:
        f.write(text)


if __name__ == "__main__":
    if sys.argv[1] != "stateful":
        raise SystemExit(f"unknown mode {sys.argv[1]!r}")
    main(sys.argv[2], sys.argv[3], int(sys.argv[4]))
