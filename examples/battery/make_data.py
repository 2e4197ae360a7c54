"""Battery fleet data from PyBaMM: drive cycles of degrading LG M50 cells.

    python examples/battery/make_data.py [out=data/battery] [cycles=20] [units=4]

Each cell (unit) runs ``cycles`` cycles; every cycle is one PyBaMM simulation of the
single-particle model with electrolyte (SPMe, Marquis et al. 2019) with the
``Chen2020`` parameter set (LG M50, 5 Ah; Chen et al. 2020, J. Electrochem. Soc.
167 080534), contact resistance on, 25 degC:

* start at rest at 90 % SOC (PyBaMM ``initial_soc=0.9``; the 90-20 % window avoids
  the steep ends of the OCV curve, where the SPMe's surface stoichiometry saturates
  on a 1C charge and no ECM of this size follows it);
* discharge: a seeded sequence of pulses, 30-200 s each, from
  {rest, 0.5C, 1C, 1.5C, 2C discharge, 0.5C regenerative charge}, until 70 % of that
  cycle's capacity is out;
* charge: constant current near 1C returning exactly the charge taken out (so the
  next cycle's 90 % start is the same state of charge), then 5 min rest.

Degradation (per unit, linear in the cycle number ``k``):

* capacity fade by loss of active material: both electrodes' active-material volume
  fractions are scaled by ``f_k = 1 - fade * k`` (``fade`` 0.4-1.2 % per cycle);
* resistance growth: the contact resistance is ``growth * k`` (``growth`` 0.3-1.0
  mOhm per cycle).

Truth columns (the ECM has model error against the SPMe, so "true" needs a rule):

* ``Q_true`` [Ah]: the cell's capacity between its 0 % and 100 % SOC (the
  stoichiometries at 2.5 V and 4.2 V at equilibrium, PyBaMM's
  ``get_min_max_stoichiometries``), from the degraded parameters:
  ``(x100 - x0) c_n,max eps_n L_n A F / 3600``. Since both electrodes shrink by the
  same factor the stoichiometry window, and the OCV(SOC) curve, do not change.
* ``R0_true`` [Ohm]: the ECM's R0 fitted to the fresh cell (``model.R0_FRESH``, by
  ``fit_ecm.py``) plus that cycle's added contact resistance. Loss of active
  material also raises the SPMe's kinetic and diffusion overpotentials slightly;
  that part is model error, not in the truth.
* ``soc_true``: ``0.9 - (discharged charge) / Q_true``.

Columns: ``unit, cycle, time [s], current [A] (discharge positive; the mean over
the step), dt [s], voltage [V]`` (PyBaMM's terminal voltage + Gaussian noise of
``NOISE_STD`` = 2 mV, seeded) and the truth columns. Sampling every 10 s.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

DT = 10.0  # [s] sampling period
NOISE_STD = 0.002  # [V] voltmeter noise
SOC_START = 0.9  # every cycle starts at rest at this SOC
DEPTH = 0.7  # share of the cycle's capacity discharged (down to SOC 0.2)
SEED = 2024
C_RATE_CHOICES = np.array([0.0, 0.5, 1.0, 1.5, 2.0, -0.5])
C_RATE_WEIGHTS = np.array([0.15, 0.2, 0.25, 0.15, 0.1, 0.15])
EPS_N, EPS_P = 0.75, 0.665  # Chen2020 active-material volume fractions
FARADAY = 96485.33212
CHARGE_C = 0.5  # charge C-rate


def unit_rates(num_units: int) -> list[tuple[float, float]]:
    """``[(fade per cycle, contact-resistance growth per cycle [Ohm])]`` per unit,
    spread evenly so the fleet covers slow to fast ageing."""
    fade = np.linspace(0.004, 0.012, num_units)
    growth = np.linspace(0.0003, 0.0010, num_units)[::-1]
    return [(float(a), float(b)) for a, b in zip(fade, growth, strict=True)]


def parameters(fade_factor: float, contact: float):
    """Chen2020 with the active material scaled and the contact resistance set."""
    import pybamm

    p = pybamm.ParameterValues("Chen2020")
    p.update(
        {
            "Negative electrode active material volume fraction": EPS_N * fade_factor,
            "Positive electrode active material volume fraction": EPS_P * fade_factor,
            "Contact resistance [Ohm]": contact,
            # the charge end overshoots 4.2 V by its overpotential: do not stop there
            "Lower voltage cut-off [V]": 2.0,
            "Upper voltage cut-off [V]": 4.6,
        },
        check_already_exists=False,
    )
    return p


def capacity(p) -> float:
    """``[Ah]`` between the 0 % and 100 % SOC stoichiometries (module docstring)."""
    import pybamm

    x0, x100, _, _ = pybamm.lithium_ion.get_min_max_stoichiometries(p)
    volume = (
        p["Negative electrode thickness [m]"]
        * p["Electrode height [m]"]
        * p["Electrode width [m]"]
    )
    c_max = p["Maximum concentration in negative electrode [mol.m-3]"]
    eps = p["Negative electrode active material volume fraction"]
    return float((x100 - x0) * c_max * eps * volume * FARADAY / 3600.0)


def current_profile(rng, q_cell: float, q_fresh: float) -> np.ndarray:
    """``[T]`` current per sample [A] of one cycle (module docstring)."""
    steps, out = [], 0.0
    while out < DEPTH * q_cell:
        n = int(rng.integers(3, 21))
        amps = float(rng.choice(C_RATE_CHOICES, p=C_RATE_WEIGHTS)) * q_fresh
        if amps > 0:  # the last pulse stops once the depth is reached
            n = min(n, int(np.ceil((DEPTH * q_cell - out) * 3600 / (amps * DT))))
        steps.append(np.full(n, amps))
        out += amps * n * DT / 3600.0
    n_charge = int(np.ceil(out * 3600.0 / (CHARGE_C * q_fresh * DT)))
    steps.append(np.full(n_charge, -out * 3600.0 / (n_charge * DT)))
    steps.append(np.zeros(int(300 / DT)))
    return np.concatenate(steps)


def simulate(p, current: np.ndarray) -> dict:
    """One cycle in PyBaMM's SPMe: ``current [T]`` held over each ``DT`` step.

    Returns ``{"voltage" [T], "discharged" [T] (A.h)}`` at the end of each step.
    """
    import pybamm

    num = current.shape[0]
    # steps at the sample instants, 1 ms ramps (the interpolant needs increasing t)
    edges = np.arange(num) * DT
    t_knots = np.concatenate([[0.0], np.ravel(np.column_stack([edges[1:], edges[1:] + 1e-3])), [num * DT]])  # fmt: skip
    i_knots = np.concatenate([[current[0]], np.ravel(np.column_stack([current[:-1], current[1:]])), [current[-1]]])  # fmt: skip
    p = p.copy()
    p["Current function [A]"] = pybamm.Interpolant(
        t_knots, i_knots, pybamm.t, interpolator="linear"
    )
    model = pybamm.lithium_ion.SPMe({"contact resistance": "true"})
    sim = pybamm.Simulation(model, parameter_values=p)
    t_eval = np.arange(num + 1) * DT
    sol = sim.solve([0.0, num * DT], initial_soc=SOC_START, t_interp=t_eval)
    if sol.t[-1] < num * DT - 1e-6:
        raise RuntimeError(f"PyBaMM stopped at t = {sol.t[-1]:.0f} s: {sol.termination}")
    return {
        "voltage": np.asarray(sol["Voltage [V]"](t_eval[1:])),
        "discharged": np.asarray(sol["Discharge capacity [A.h]"](t_eval[1:])),
    }


def make_unit(unit: int, rates, cycles: int, q_fresh: float, rng) -> dict:
    """Every cycle of one unit, concatenated (columns of the CSV)."""
    fade, growth = rates
    cols = {k: [] for k in ("cycle", "current", "voltage", "Q_true", "R0_true", "soc_true")}  # fmt: skip
    from model import R0_FRESH

    for k in range(cycles):
        p = parameters(1.0 - fade * k, growth * k)
        q_cell = capacity(p)
        current = current_profile(rng, q_cell, q_fresh)
        sim = simulate(p, current)
        n = current.shape[0]
        cols["cycle"].append(np.full(n, k))
        cols["current"].append(current)
        cols["voltage"].append(sim["voltage"] + NOISE_STD * rng.standard_normal(n))
        cols["Q_true"].append(np.full(n, q_cell))
        cols["R0_true"].append(np.full(n, R0_FRESH + growth * k))
        cols["soc_true"].append(SOC_START - sim["discharged"] / q_cell)
    out = {k: np.concatenate(v) for k, v in cols.items()}
    n = out["current"].shape[0]
    out["unit"] = np.full(n, unit)
    out["dt"] = np.full(n, DT)
    out["time"] = np.arange(1, n + 1) * DT
    return out


def main(argv: list[str] | None = None) -> str:
    """Write ``<out>/fleet.csv`` (skipped when it exists); returns its path."""
    import pandas as pd

    opts = {"out": "data/battery", "cycles": "20", "units": "4"}
    for token in argv or []:
        key, sep, value = token.partition("=")
        if not sep or key not in opts:
            raise SystemExit(f"usage: make_data.py [out=DIR] [cycles=N] [units=N]; got {token!r}")  # fmt: skip
        opts[key] = value
    path = os.path.join(opts["out"], "fleet.csv")
    if os.path.exists(path):
        print(f"{path} exists (delete it to regenerate)")
        return path
    os.makedirs(opts["out"], exist_ok=True)
    cycles, units = int(opts["cycles"]), int(opts["units"])
    q_fresh = capacity(parameters(1.0, 0.0))
    rng = np.random.default_rng(SEED)
    frames = []
    for unit, rates in enumerate(unit_rates(units), start=1):
        start = time.perf_counter()
        frames.append(pd.DataFrame(make_unit(unit, rates, cycles, q_fresh, rng)))
        print(
            f"unit {unit}/{units}: fade {rates[0]:.2%}/cycle, +{rates[1] * 1e3:.2f} "
            f"mOhm/cycle, {len(frames[-1])} rows, {time.perf_counter() - start:.0f} s",
            flush=True,
        )
    frame = pd.concat(frames, ignore_index=True)
    order = ["unit", "cycle", "time", "current", "dt", "voltage", "Q_true", "R0_true", "soc_true"]  # fmt: skip
    frame[order].to_csv(path, index=False)
    print(f"wrote {path}: {len(frame)} rows")
    return path


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    main(sys.argv[1:])
