"""Load the NASA C-MAPSS FD001 / FD002 text files and print a JSON summary.

For each of ``train_FD00x.txt`` / ``test_FD00x.txt`` (with ``RUL_FD00x.txt``): rows,
units and RUL range; for ``train_FD002.txt``: the six operating conditions (clustered on
the op settings rounded to 1 kft, 0.01 Mach, 1 % TRA) with their row counts and the mean
T24, T30, T50, P30 and Nc. Compare with data_facts.md §1.3.

Usage::

    python experiments/load_cmapss.py [--data-dir /work/shared/data/cmapss]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jaxcal.models.turbofan.data.cmapss_text import load_cmapss_text
from jaxcal.models.turbofan.data.record import Record

DEFAULT_DATA_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmapss"
SUBSETS = ("FD001", "FD002")
CONDITION_SENSORS = ("T24", "T30", "T50", "P30", "Nc")


def condition_means(record: Record, sensors=CONDITION_SENSORS) -> list[dict]:
    """Row count and sensor means per operating condition (rounded op settings)."""
    keys = np.stack(
        [
            np.round(record.extras["op1_kft"]),
            np.round(record.extras["op2"], 2),
            np.round(record.extras["op3"]),
        ],
        axis=1,
    )
    conditions, inverse = np.unique(keys, axis=0, return_inverse=True)
    values = record.columns(sensors)
    out = []
    for i, (alt_kft, mach, tra) in enumerate(conditions):
        rows = inverse.ravel() == i
        means = values[rows].mean(axis=0)
        out.append(
            {
                "alt_kft": float(alt_kft),
                "mach": float(mach),
                "tra": float(tra),
                "rows": int(rows.sum()),
                "means": {
                    s: round(float(m), 3) for s, m in zip(sensors, means, strict=True)
                },
            }
        )
    return out


def summarise(data_dir) -> dict:
    """Per-file sizes of FD001 / FD002 and the FD002 condition means.

    Args:
        data_dir: directory holding the NASA ``*_FD001.txt`` / ``*_FD002.txt`` files.

    Returns:
        ``{"data_dir", "files": {name: {"rows", "units", "rul_min", "rul_max"}},
        "FD002_conditions": [...]}``.
    """
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise FileNotFoundError(f"C-MAPSS data directory not found: {data_dir}")
    files, records = {}, {}
    for subset in SUBSETS:
        for kind in ("train", "test"):
            path = data_dir / f"{kind}_{subset}.txt"
            rul_path = data_dir / f"RUL_{subset}.txt" if kind == "test" else None
            record = load_cmapss_text(path, rul_path)
            records[path.name] = record
            files[path.name] = {
                "rows": len(record),
                "units": len(record.units),
                "rul_min": int(record.rul.min()),
                "rul_max": int(record.rul.max()),
            }
    return {
        "data_dir": str(data_dir),
        "files": files,
        "FD002_conditions": condition_means(records["train_FD002.txt"]),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default=str(DEFAULT_DATA_DIR))
    args = parser.parse_args(argv)
    try:
        summary = summarise(args.data_dir)
    except FileNotFoundError as err:
        sys.exit(f"error: {err}")
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
