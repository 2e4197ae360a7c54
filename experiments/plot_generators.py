"""Figures of the condition and degradation generators (paper Fig. 2, Dataset #1).

Draws a Dataset #1-like fleet of 10 units in which only HPT_eff_mod degrades (units 1,
4, 7 and 9 fly short, low flights of class 1, the others classes 2 and 3), and writes

* ``results/data/flight_profile.png``: alt / Mach / TRA of one flight per class;
* ``results/data/theta_trajectories_cmapss.png``: HPT_eff_mod against cycle.

It also prints the realised ranges of w over 300 flights next to the paper's Table 1,
and, when the N-CMAPSS ground-truth CSV is at hand, its statistics next to the generator
defaults of ``jaxcal.models.turbofan.data.ground_truth``.

Usage::

    python experiments/plot_generators.py [--seed 0] [--out results/data]
        [--ground-truth /work/shared/data/ncmapss/fault_ground_truth.csv]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.models.turbofan.data import ground_truth
from jaxcal.models.turbofan.data.degradation import (
    DegradationConfig,
    sample_unit_degradation,
)
from jaxcal.models.turbofan.data.flights import FlightConfig, sample_flight
from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES
from jaxcal.plotting import plot_flight_profiles, plot_health_trajectories

REPO = Path(__file__).resolve().parents[1]
DEFAULT_GROUND_TRUTH = (
    REPO.parent / "shared" / "data" / "ncmapss" / "fault_ground_truth.csv"
)
# Units 1, 4, 7, 9 are the E2E baseline's labelled units: shorter, lower flights.
FLEET_CLASSES = (1, 3, 2, 1, 3, 2, 1, 3, 1, 2)
PAPER_RANGES = {"alt": (10.0e3, 35.0e3), "Mach": (0.26, 0.75), "TRA": (23.6, 87.8)}


def fleet_degradation(key, cfg: DegradationConfig, num_cycles_max: int = 100):
    """Degradation of the 10-unit fleet, vmapped over units."""
    keys = jax.random.split(key, len(FLEET_CLASSES))
    sample = jax.vmap(lambda k, c: sample_unit_degradation(k, num_cycles_max, cfg, c))
    return jax.jit(sample)(keys, jnp.asarray(FLEET_CLASSES))


def flights(key, classes, cfg: FlightConfig):
    """One flight per class, vmapped over keys."""
    keys = jax.random.split(key, len(classes))
    sample = jax.vmap(lambda k, c: sample_flight(k, c, cfg))
    return jax.jit(sample)(keys, jnp.asarray(classes))


def print_ranges(key, num_flights: int = 300) -> None:
    """Realised w ranges over many flights (10 s sampling) vs. the paper's Table 1."""
    classes = np.resize(np.asarray(FLEET_CLASSES), num_flights)
    out = flights(key, classes, FlightConfig(dt_s=10.0))
    w, mask = np.asarray(out.w), np.asarray(out.mask)
    for j, name in enumerate(("alt", "Mach", "TRA", "T2")):
        v = w[..., j][mask]
        paper = PAPER_RANGES.get(name)
        ref = f"   paper {paper[0]:g} - {paper[1]:g}" if paper else ""
        print(f"  {name:5s} {v.min():10.4g} - {v.max():10.4g}{ref}")
    for c in (1, 2, 3):
        hours = np.asarray(out.duration_s)[classes == c] / 3600.0
        print(
            f"  Fc {c}: recorded {hours.min():.2f} - {hours.max():.2f} h above 10 kft"
        )


def print_ground_truth(path: Path) -> None:
    """Statistics of the real N-CMAPSS engines next to the code constants."""
    if not path.is_file():
        print(f"ground-truth check skipped: {path} not found")
        return
    engines = ground_truth.load_fault_ground_truth(path)
    stats = ground_truth.summarize_ground_truth(engines)
    hpt = ground_truth.summarize_ground_truth(engines, components=("HPT",))
    print(f"ground truth ({stats.num_engines} engines, {path}):")
    for c in ground_truth.FLIGHT_CLASSES:
        print(
            f"  Fc {c}: onset {stats.onset_by_class[c]} "
            f"(code {ground_truth.ONSET_CYCLES_BY_CLASS[c - 1]}), "
            f"EOL {stats.eol_by_class[c]} "
            f"(code {ground_truth.EOL_CYCLES_BY_CLASS[c - 1]})"
        )
    print(
        f"  HPT_eff EOL, HPT-only engines: {hpt.eol_delta_range['HPT_eff_mod']} "
        f"(code default {ground_truth.DEFAULT_EOL_THETA_RANGE['HPT_eff_mod']})"
    )
    mismatched = [
        n
        for n, r in stats.eol_delta_range.items()
        if not np.allclose(r, ground_truth.EOL_DELTA_RANGE[n])
    ]
    print(f"  EOL_DELTA_RANGE mismatches vs. CSV: {mismatched or 'none'}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=REPO / "results" / "data")
    parser.add_argument("--ground-truth", type=Path, default=DEFAULT_GROUND_TRUTH)
    args = parser.parse_args(argv)

    key = jax.random.key(args.seed)
    key_fleet, key_profile, key_ranges = jax.random.split(key, 3)
    deg_cfg = DegradationConfig(degrading=("HPT_eff_mod",))
    fleet = fleet_degradation(key_fleet, deg_cfg)
    flight_cfg = FlightConfig(dt_s=1.0)
    profile = flights(key_profile, (1, 2, 3), flight_cfg)
    t = np.arange(flight_cfg.num_steps) * flight_cfg.dt_s

    profile_path = plot_flight_profiles(
        args.out / "flight_profile.png",
        t,
        np.asarray(profile.w),
        mask=np.asarray(profile.mask),
        labels=["Fc 1 (1-3 h)", "Fc 2 (3-5 h)", "Fc 3 (5-7 h)"],
        title="Generated flight profiles (recorded above 10,000 ft, 1 Hz)",
    )
    theta_path = plot_health_trajectories(
        args.out / "theta_trajectories_cmapss.png",
        np.asarray(fleet.cycle),
        np.asarray(fleet.theta),
        HEALTH_NAMES,
        mask=np.asarray(fleet.mask),
        select=("HPT_eff_mod",),
        onset=np.asarray(fleet.onset_cycle),
        unit_labels=[f"unit {u + 1} (Fc {c})" for u, c in enumerate(FLEET_CLASSES)],
        title="Dataset #1-like fleet: HPT_eff_mod (circles: abnormal onset t_s)",
    )
    print("fleet EOL cycles:", np.asarray(fleet.eol_cycle).tolist())
    print("fleet onset cycles:", np.asarray(fleet.onset_cycle).tolist())
    print("realised w ranges over 300 flights:")
    print_ranges(key_ranges)
    print_ground_truth(args.ground_truth)
    print(profile_path)
    print(theta_path)


if __name__ == "__main__":
    main()
