"""Prognosis on a fleet with two fault modes (HPC or fan), in NASA's C-MAPSS text form.

NASA's FD003 and FD004 mix two fault modes: a unit's HPC or its fan degrades. They are
not in ``../shared/``; this experiment writes a fleet of that shape from the ``cmapss``
engine itself, so that the command a user types on such a file can be scored against
a known truth:

* 100 training units run to failure and 100 test units cut short, sea-level conditions
  as FD001's (altitude, Mach and TRA drawn about FD001's means and spreads; FD003's
  shape), or with ``conditions=FD002`` each cycle's conditions drawn from FD002's rows
  (its six operating conditions: FD004's shape);
* each unit degrades its HPC (efficiency and flow) or its fan (efficiency and flow),
  half of the units each, along the run-to-failure law of
  :mod:`jaxcal.models.turbofan.data.degradation` (a random initial wear, a linear
  phase, then an exponential one; ``theta_j = m_j (1 - h)`` reaches its end-of-life
  value ``m_j`` at the last cycle);
* every parameter starts at a small random offset (manufacturing spread), and the
  outputs carry white noise of FD001's size (each sensor's cycle-to-cycle spread in
  the first 40 cycles of FD001's units).

Each test unit's true RUL is its life minus its last cycle (``RUL_two_modes.txt``).
The prognosis is run three times through the command line's function (:data:`RUNS`):
with the HPC and fan pairs calibrated (the default,
:data:`jaxcal.models.turbofan.model.PROGNOSIS_THETA`), the same with one Gaussian
trend prior over all units (as before the fault modes' mixture), and with the HPC pair
only; each is scored: RMSE, PHM08, coverage, and whether the named driver is the
unit's fault mode.

Usage::

    python experiments/prognosis_two_modes.py [seed=0] [units=100]
        [data=data/two_modes] [out=results/prognosis/two_modes]
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.cache import enable_compilation_cache
from jaxcal.models import load
from jaxcal.models.turbofan.data.cmapss_text import EXTRA_MAP, SENSOR_MAP
from jaxcal.models.turbofan.model import PROGNOSIS_OUTPUTS, PROGNOSIS_THETA
from jaxcal.precision import enable_x64
from jaxcal.prognosis import PrognosisConfig, degradation, prognose, read_truth, score
from jaxcal.prognosis.report import write_prognosis
from jaxcal.settings import config_to_dict, parse_overrides

# End-of-life values (most, least negative) per mode: near what the UKF reads at the
# last cycles of FD001's units (HPC) and a fan loss of the same order.
MODES = {
    "HPC": {"HPC_eff_mod": (-0.018, -0.014), "HPC_flow_mod": (-0.025, -0.010)},
    "fan": {"fan_eff_mod": (-0.035, -0.027), "fan_flow_mod": (-0.022, -0.016)},
}
# FD001's cycle-to-cycle noise (std of first differences / sqrt 2, first 40 cycles,
# the median over units) of the sensors the prognosis reads
NOISE = {
    "T24": 0.29, "T30": 4.0, "T50": 3.9, "P30": 0.41, "Nc": 4.1, "NRc": 3.0,
    "BPR": 0.020, "W31": 0.099, "W32": 0.061,
}  # fmt: skip
OTHER_NOISE = 5e-4  # relative, the sensors the prognosis does not read
HT_BLEED = 392.0
# the two choices of calibrated parameters compared (one of them the C-MAPSS default)
HPC_FAN = ("HPC_eff_mod", "HPC_flow_mod", "fan_eff_mod", "fan_flow_mod")
# label -> (theta, the fault modes' mixture prior)
RUNS = {
    "hpc_fan": (HPC_FAN, True),
    "hpc_fan_one_gaussian": (HPC_FAN, False),
    "hpc_only": (("HPC_eff_mod", "HPC_flow_mod"), True),
}  # C-MAPSS's bleed enthalpy column (no counterpart in the engine)


@dataclasses.dataclass(frozen=True)
class TwoModesConfig:
    seed: int = 0
    units: int = 100  # training units; as many test units
    life: tuple[int, int] = (128, 362)  # FD001's range of training lives
    # operating conditions: FD001's (sea level) or FD002's six (FD004's shape), each
    # cycle's drawn from that file's rows
    conditions: str = "FD001"
    data_dir: str = os.path.normpath(
        os.path.join(
            os.path.dirname(os.path.abspath(__file__)), "../../shared/data/cmapss"
        )
    )
    data: str = "data/two_modes"
    out: str = "results/prognosis/two_modes"


def _health(rng, life: int) -> np.ndarray:
    """``1 - h(t)`` for t = 1..life: the run-to-failure law of the turbofan's generator
    (its module docstring): 0 -> 1 at the last cycle."""
    d = rng.uniform(0.0, 0.1)
    u = rng.uniform(0.15, 0.35)
    b = rng.uniform(1.1, 1.6)
    onset = rng.uniform(0.3, 0.7) * life
    t = np.arange(1, life + 1, dtype=float)
    r = u * (1 - d) / life
    a = np.log(1 + (1 - u) * (1 - d)) / (life - onset) ** b
    h = 1 - d - r * t - (np.exp(a * np.clip(t - onset, 0, None) ** b) - 1)
    return 1 - h


def _units(rng, cfg: TwoModesConfig, names, test: bool):
    """Per unit: (mode, theta [T, P], cut RUL or 0)."""
    out = []
    for k in range(cfg.units):
        mode = "HPC" if k % 2 == 0 else "fan"
        life = int(rng.integers(cfg.life[0], cfg.life[1] + 1))
        loss = _health(rng, life)
        theta = np.zeros((life, len(names)))
        theta += rng.uniform(-0.002, 0.0, len(names))  # manufacturing spread
        for name, (lo, hi) in MODES[mode].items():
            theta[:, names.index(name)] += rng.uniform(lo, hi) * loss
        rul = 0
        if test:
            rul = int(rng.integers(7, min(150, life - 30)))
            theta = theta[: life - rul]
        out.append((mode, theta, rul))
    return out


def _conditions(cfg: TwoModesConfig, rng, n: int) -> np.ndarray:
    """``[n, 4]`` altitude (ft), Mach, TRA and T2 of ``n`` cycles: FD001's sea level
    with its jitter, or (``conditions=FD002``) rows drawn from FD002's six."""
    if cfg.conditions == "FD001":
        alt = rng.normal(0.0, 2.2, n)  # ft: FD001's op1 spread, 0.0022 kft
        mach = rng.normal(0.0, 2.9e-4, n)
        return np.stack([alt, mach, np.full(n, 100.0), np.full(n, 518.67)], 1)
    if cfg.conditions != "FD002":
        raise ValueError(f"conditions must be FD001 or FD002, got {cfg.conditions!r}")
    table = np.loadtxt(os.path.join(cfg.data_dir, "train_FD002.txt"))
    rows = table[rng.integers(0, len(table), n)]
    return np.stack([rows[:, 2] * 1000.0, rows[:, 3], rows[:, 4], rows[:, 5]], 1)


def _write(path: str, model, units, rng, cfg: TwoModesConfig) -> None:
    """The units' rows in C-MAPSS's 26 columns (one vmapped evaluation of them all)."""
    theta = np.concatenate([th for _, th, _ in units])
    n = theta.shape[0]
    uid = np.concatenate(
        [np.full(len(th), k + 1) for k, (_, th, _) in enumerate(units)]
    )
    cycle = np.concatenate([np.arange(1, len(th) + 1) for _, th, _ in units])
    w = _conditions(cfg, rng, n)
    evaluate = jax.jit(jax.vmap(lambda w, th: model.evaluate(w, th)[0]))
    x = np.asarray(evaluate(jnp.asarray(w), jnp.asarray(theta)))
    if not np.isfinite(x).all():
        raise RuntimeError("the engine did not converge on some rows")
    noisy = {}
    for j, name in enumerate(model.output_names):
        std = NOISE.get(name, OTHER_NOISE * abs(np.mean(x[:, j])))
        noisy[name] = x[:, j] + rng.normal(0.0, std, n)
    cols = {1: w[:, 3]}
    cols.update({s: noisy[name] for s, name in SENSOR_MAP.items()})
    extra = {"Ps30_cmapss": noisy["Ps30"], "phi_cmapss": noisy["phi"]}
    for s, key in EXTRA_MAP.items():
        cols[s] = extra.get(key, np.full(n, HT_BLEED))
    table = np.column_stack(
        [uid, cycle, w[:, 0] / 1000.0, w[:, 1], w[:, 2]]
        + [cols[s] for s in range(1, 22)]
    )
    tmp = path + ".tmp"
    np.savetxt(tmp, table, fmt="%.8g")
    os.replace(tmp, path)


@contextlib.contextmanager
def _mixture(on: bool):
    """The fault modes' mixture prior, or (``on=False``) one Gaussian over every unit:
    the degradation model's mode finder swapped for one that finds a single mode."""
    if on:
        yield
        return
    kept = degradation._modes
    degradation._modes = lambda carriers, need: kept(carriers, carriers.shape[0] + 1)
    try:
        yield
    finally:
        degradation._modes = kept


def _driver_hits(pred, modes) -> float:
    """Share of test units whose named driver belongs to their fault mode."""
    hits = [d in MODES[m] for d, m in zip(pred.driver, modes, strict=True)]
    return float(np.mean(hits))


def _run(cfg, files, theta, modes, label):
    train, test, truth_path = files
    start = time.perf_counter()
    result = prognose(
        "cmapss", train, test, theta=theta, outputs=PROGNOSIS_OUTPUTS,
        config=PrognosisConfig(seed=cfg.seed),
    )  # fmt: skip
    seconds = time.perf_counter() - start
    pred = result.prediction
    truth = read_truth(truth_path, pred.unit.size)
    scores = score(pred.rul, pred.rul_low, pred.rul_high, truth)
    scores.update(
        seconds=seconds, driver_is_mode=_driver_hits(pred, modes),
        theta=list(theta),
    )  # fmt: skip
    for mode in MODES:
        sel = np.array([m == mode for m in modes])
        err = pred.rul[sel] - truth[sel]
        scores[f"rmse_{mode}"] = float(np.sqrt(np.mean(err**2)))
    write_prognosis(
        os.path.join(cfg.out, label), result, truth=truth,
        source={"train": train, "test": test, "truth": truth_path},
        config={**config_to_dict(cfg), "theta": list(theta)},
        unit_figures=list(pred.unit[:6]),
    )  # fmt: skip
    return scores


def _big(v: float) -> str:
    """A score as an integer, or in powers of ten past seven digits."""
    return f"{v:.0f}" if v < 1e7 else f"{v:.2e}"


def _is_default(label: str, row: dict) -> bool:
    return RUNS[label][1] and tuple(row["theta"]) == PROGNOSIS_THETA


def _readme(rows: dict, argv, conditions: str = "FD001") -> str:
    shape = {
        "FD001": "FD003's shape: one operating condition, FD001's sea level",
        "FD002": "FD004's shape: six operating conditions, drawn from FD002's rows",
    }[conditions]
    lines = [
        f"# Prognosis on a fleet with two fault modes ({shape})",
        "",
        f"`python experiments/prognosis_two_modes.py {' '.join(argv)}`".replace(
            " `", "`"
        )
        + ": 100 run-to-failure and 100 test units written by the `cmapss` engine in "
        "C-MAPSS's text form, half of them losing HPC efficiency and flow, half fan "
        "efficiency and flow (the experiment's docstring). Each row is one run of "
        "`jaxcal.prognose` with the `theta` named; `one Gaussian`: the trend prior of "
        "one Gaussian over all units, as before the fault modes' mixture "
        "(`jaxcal/prognosis/degradation.py`); `s`: the run's wall seconds, calibration "
        "included (the first run compiles the four-parameter programs the second "
        "reuses; the machine shared with another job).",
        "",
        "| theta | RMSE | RMSE, HPC units | RMSE, fan units | PHM08 | coverage | "
        "driver is the unit's mode | s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, s in rows.items():
        lines.append(
            f"| {label}{' (the default)' if _is_default(label, s) else ''}"
            f": {', '.join(s['theta'])} | {s['rmse']:.2f} | "
            f"{s['rmse_HPC']:.2f} | {s['rmse_fan']:.2f} | {_big(s['phm08_score'])} | "
            f"{s['coverage']:.2f} | {s['driver_is_mode']:.2f} | {s['seconds']:.0f} |"
        )
    lines += ["", "Reports: " + ", ".join(f"[{k}]({k}/report.md)" for k in rows), ""]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    try:
        cfg = parse_overrides(argv, TwoModesConfig())
    except ValueError as err:
        print(f"prognosis_two_modes: {err}", file=sys.stderr)
        return 2
    enable_x64()
    enable_compilation_cache()
    model = load("cmapss")
    names = list(model.parameter_names)
    rng = np.random.default_rng(cfg.seed)
    train_units = _units(rng, cfg, names, test=False)
    test_units = _units(rng, cfg, names, test=True)
    os.makedirs(cfg.data, exist_ok=True)
    files = tuple(
        os.path.join(cfg.data, f"{k}_two_modes.txt") for k in ("train", "test", "RUL")
    )
    _write(files[0], model, train_units, rng, cfg)
    _write(files[1], model, test_units, rng, cfg)
    with open(files[2], "w") as f:
        f.write("\n".join(str(rul) for _, _, rul in test_units) + "\n")
    modes = [m for m, _, _ in test_units]
    rows = {}
    for label, (theta, mixture) in RUNS.items():
        with _mixture(mixture):
            rows[label] = _run(cfg, files, theta, modes, label)
        print(f"{label}: {json.dumps(rows[label])}", flush=True)
    from jaxcal.diagnosis.report.write import write_text

    write_text(os.path.join(cfg.out, "results.json"), json.dumps(rows, indent=1))
    write_text(os.path.join(cfg.out, "README.md"), _readme(rows, argv, cfg.conditions))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
