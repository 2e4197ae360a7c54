"""Figures of a generated data set (paper Fig. 2 for Dataset #1, theta grid for #2).

Reads a file written by ``python -m jaxcal.generate`` (or any N-CMAPSS file) and writes

* ``results/data/<name>_flight_profile.png``: alt / Mach / TRA of a few flights (fleet:
  the first flight of the first unit of each flight class; scenarios: one scenario on
  each cruise flight);
* ``results/data/<name>_theta.png``: fleet: the degrading health modifiers of every unit
  against cycle (circles: abnormal onset, hs 1 -> 0); scenarios: the modifiers of every
  scenario stacked one after the other (the paper's Dataset #2 figures).

``<name>`` is the file's ``dataset`` attribute (else the file stem). Only W, T and A are
read, so a 6.5 M-row file costs a few hundred MB at most. It also prints the W ranges
next to the paper's Table 1.

Usage::

    python experiments/plot_dataset.py data/cmapss.h5 [--out results/data]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jaxcal.models.turbofan.data.ncmapss_io import load_ncmapss, ncmapss_info
from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES
from jaxcal.plotting import (
    plot_flight_profiles,
    plot_health_trajectories,
    plot_stacked_traces,
)

REPO = Path(__file__).resolve().parents[1]
PAPER_W_RANGES = {  # Table 1: alt [ft], Mach, TRA [%]
    "cmapss": ((10.0e3, 35.0e3), (0.26, 0.75), (23.6, 87.8)),
    "agtf30": ((25.7e3, 29.0e3), (0.67, 0.74), (69.1, 82.4)),
}


def _pad_flights(records, rate_hz):
    """[F, T, 4] conditions, [F, T] mask and [T] time of flights of unequal length."""
    length = max(r.num_rows for r in records)
    w = np.zeros((len(records), length, 4))
    mask = np.zeros((len(records), length), bool)
    for i, r in enumerate(records):
        w[i, : r.num_rows], mask[i, : r.num_rows] = r.w, True
    return w, mask, np.arange(length) / rate_hz


def _moving(theta):
    """Names of the health modifiers that are not zero everywhere."""
    return [n for j, n in enumerate(HEALTH_NAMES) if np.any(theta[:, j] != 0)]


def plot_fleet(path, info, name, out):
    """Fleet figures: flights per class and theta against cycle for every unit."""
    recs = [load_ncmapss(path, s, sensors=()) for s in info["splits"]]
    rate = info["sample_rate_hz"]
    flights, labels = [], []
    for fc in (1, 2, 3):
        for rec in recs:
            units = np.unique(rec.unit[rec.flight_class == fc])
            if units.size:
                sel = (rec.unit == units[0]) & (rec.cycle == 1)
                flights.append(rec.take(sel))
                labels.append(f"unit {units[0]}, Fc {fc}, cycle 1")
                break
    w, mask, t = _pad_flights(flights, rate)
    profile = plot_flight_profiles(
        out / f"{name}_flight_profile.png", t, w, mask=mask, labels=labels,
        title=f"{name}: first flight per flight class ({rate:.3g} Hz)",
    )  # fmt: skip
    units = np.concatenate([rec.units for rec in recs])
    num_cycles = max(int(rec.cycle.max()) for rec in recs)
    theta = np.zeros((units.size, num_cycles, len(HEALTH_NAMES)))
    valid = np.zeros((units.size, num_cycles), bool)
    onset = np.full(units.size, num_cycles + 1)
    for i, u in enumerate(units):
        rec = next(r for r in recs if u in r.units).select_units([u])
        first = np.unique(rec.cycle, return_index=True)[1]  # theta is per cycle
        cyc = rec.cycle[first] - 1
        theta[i, cyc], valid[i, cyc] = rec.theta[first], True
        abnormal = rec.cycle[rec.hs == 0]
        onset[i] = abnormal.min() if abnormal.size else num_cycles + 1
    select = _moving(theta[valid])
    theta_png = plot_health_trajectories(
        out / f"{name}_theta.png", np.arange(1, num_cycles + 1), theta, HEALTH_NAMES,
        mask=valid, select=select or None, onset=onset,
        unit_labels=[f"unit {u}" for u in units],
        title=f"{name}: health modifiers (circles: abnormal onset)",
    )  # fmt: skip
    return profile, theta_png, recs


def plot_scenarios(path, info, name, out):
    """Scenario figures: one scenario per flight, stacked theta of every scenario."""
    config = json.loads(info["attrs"]["config"])
    steps = int(config["flight_steps"])
    # one row per scenario: every scenario has exactly `steps` rows
    heads = [load_ncmapss(path, s, sensors=(), stride=steps) for s in info["splits"]]
    flights, labels = [], []
    for fc in np.unique(np.concatenate([h.flight_class for h in heads])):
        split, head = next(
            (s, h) for s, h in zip(info["splits"], heads, strict=True)
            if np.any(h.flight_class == fc)
        )  # fmt: skip
        unit = int(head.unit[head.flight_class == fc][0])
        flights.append(load_ncmapss(path, split, units=[unit], sensors=()))
        labels.append(f"flight {int(fc)} (scenario {unit})")
    w, mask, t = _pad_flights(flights, info["sample_rate_hz"])
    profile = plot_flight_profiles(
        out / f"{name}_flight_profile.png", t, w, mask=mask, labels=labels,
        title=f"{name}: the cruise-band flight trajectories",
    )  # fmt: skip
    order = [(s, h) for s, h in zip(info["splits"], heads, strict=True)]
    theta = np.concatenate([h.theta for _, h in order])
    select = _moving(theta) or list(HEALTH_NAMES[:1])
    cols = [HEALTH_NAMES.index(n) for n in select]
    bounds = np.cumsum([h.num_rows for _, h in order])[:-1]
    theta_png = plot_stacked_traces(
        out / f"{name}_theta.png", {}, truth=theta[:, cols], unit_boundaries=bounds,
        names=select, xlabel="scenario (dev, then test)",
        title=f"{name}: health modifiers of the {theta.shape[0]} fault scenarios",
    )  # fmt: skip
    return profile, theta_png, flights


def print_ranges(name, records):
    """Realised W ranges next to the paper's Table 1."""
    w = np.concatenate([r.w for r in records])
    paper = PAPER_W_RANGES.get(name)
    for j, label in enumerate(("alt", "Mach", "TRA", "T2")):
        ref = f"   paper {paper[j][0]:g} - {paper[j][1]:g}" if paper and j < 3 else ""
        print(f"  {label:5s} {w[:, j].min():10.4g} - {w[:, j].max():10.4g}{ref}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", type=Path, help="generated N-CMAPSS .h5 file")
    parser.add_argument("--out", type=Path, default=REPO / "results" / "data")
    parser.add_argument("--name", default=None, help="figure prefix (default: attr)")
    args = parser.parse_args(argv)

    info = ncmapss_info(args.path)
    name = args.name or info["attrs"].get("dataset") or args.path.stem
    scenarios = json.loads(info["attrs"].get("config", "{}")).get("kind") == "scenarios"
    plot = plot_scenarios if scenarios else plot_fleet
    profile, theta_png, records = plot(args.path, info, name, args.out)
    rows = {s: v["rows"] for s, v in info["splits"].items()}
    print(f"{args.path}: rows {rows}, {info['sample_rate_hz']:.3g} Hz")
    print("W ranges of the plotted rows:" if scenarios else "W ranges (all rows):")
    print_ranges(name, records)
    print(profile)
    print(theta_png)


if __name__ == "__main__":
    main()
