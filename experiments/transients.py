"""Transients are not outliers (issue 43 item 4): the diagnosis's outlier screening on
the newcomer's reactor with set-point changes and AR(1) noise.

``experiments/reactor.py``: ``units`` units of 500 samples, the conditions stepping
to a new set point every 10-40 samples, AR(1) measurement noise of coefficient 0.8;
the declared ``activity``, ``UA`` and ``dH``, the noise estimated (as a new user runs
``python -m jaxcal.diagnose``). Per seed, two fleets:

* ``clean``: nothing wild; every row the screening leaves out is a false alarm, and
  those within :data:`AROUND` rows of a set-point change are the transients of the
  issue. The same test (a reading's departure from the median of its two
  neighbours on each side, beyond 6 robust stds) applied to the residual at the
  TRUE parameters is the premise: it flags none.
* ``spikes``: the same fleet with 10-sigma spikes (the sensors' std) on one output
  of 0.5 % of the rows: each should be left out, and nothing else.

The stages are the diagnosis's own (``prepare_data``, the declared-only fit,
``drop_outliers``), so the script runs on the code before the change as well
(``PYTHONPATH=<a checkout of the previous commit>``, ``label=before``).

Usage::

    python experiments/transients.py [seeds=4] [units=6] [phi=0.8] [label=after]
        [commit=<what the label ran>] [out=results/loop]

Merges ``<label>`` into ``<out>/transients.json`` and writes ``transients.md`` from
every label there.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import reactor  # noqa: E402

import jaxcal  # noqa: E402  (the package the path points to: recorded)
from jaxcal.data.dataset import Dataset  # noqa: E402
from jaxcal.diagnosis.data.cleaning import drop_outliers  # noqa: E402
from jaxcal.diagnosis.data.prepare import prepare_data  # noqa: E402
from jaxcal.diagnosis.fitting.joint import fit_model  # noqa: E402
from jaxcal.diagnosis.kinds.terms import ModelSpec  # noqa: E402
from jaxcal.diagnosis.pipeline import LoopConfig  # noqa: E402
from jaxcal.runs.atomic import write_atomic  # noqa: E402

DECLARED = ("activity", "UA", "dH")
ROWS, PHI = 500, 0.8
AROUND = 3  # rows on each side of a set-point change its transient covers
SPIKE_SIGMA, SPIKE_SHARE = 10.0, 0.005


def _screen(model, fleet, cfg) -> tuple[np.ndarray, float]:
    """``(left_out [N] bool, seconds)``: the diagnosis's screening on ``fleet``."""
    ds = Dataset(
        w=fleet[list(reactor.CONDITIONS)].to_numpy(),
        x=fleet[list(reactor.OUTPUTS)].to_numpy(),
        condition_names=list(reactor.CONDITIONS), output_names=list(reactor.OUTPUTS),
        unit=fleet["unit"].to_numpy(), time=fleet["time"].to_numpy().astype(float),
    )  # fmt: skip
    start = time.perf_counter()
    data = prepare_data(ds, model, knots=cfg.knots, candidate_knots=cfg.candidate_knots)
    spec0 = ModelSpec(DECLARED, initial_state=True)
    null = fit_model(model, data, spec0, max_iters=cfg.max_iters)
    screened, _ = drop_outliers(model, data, spec0, null, cfg)
    seconds = time.perf_counter() - start
    # a model with memory keeps a left-out row in time, unobserved
    return data.observed.any(1) & ~screened.observed.any(1), seconds


def _changes(fleet) -> tuple[np.ndarray, np.ndarray]:
    """``(near [N], first [N])``: rows within :data:`AROUND` of a set-point change
    in their unit, and each unit's first row."""
    w = fleet[list(reactor.CONDITIONS)].to_numpy()
    unit = fleet["unit"].to_numpy()
    same = np.r_[False, unit[1:] == unit[:-1]]
    change = np.flatnonzero(same & np.r_[False, np.any(np.diff(w, axis=0), 1)])
    near = np.zeros(len(w), bool)
    for k in range(-AROUND, AROUND + 1):
        near[np.clip(change + k, 0, len(w) - 1)] = True
    return near, ~same


def _at_truth(fleet, cfg) -> int:
    """Rows the neighbour test flags on the residual at the true parameters."""
    flagged = 0
    for _, g in fleet.groupby("unit", sort=True):
        truth = np.asarray(
            reactor._SIMULATE(g[list(reactor.CONDITIONS)].to_numpy(),
                              g[list(reactor.PARAMETERS)].to_numpy())
        )  # fmt: skip
        r = g[list(reactor.OUTPUTS)].to_numpy() - truth
        padded = np.pad(r, ((2, 2), (0, 0)), mode="edge")
        window = np.lib.stride_tricks.sliding_window_view(padded, 5, axis=0)
        dep = r - np.median(np.delete(window, 2, axis=2), axis=2)
        flagged += int(np.any(np.abs(dep) > cfg.outlier_z * _mad(dep), axis=1).sum())
    return flagged


def _mad(x):
    return 1.4826 * np.median(np.abs(x - np.median(x, 0)), 0)


def _spiked(fleet, seed):
    rng = np.random.default_rng([seed, 43])
    n = len(fleet)
    rows = np.sort(rng.choice(n, max(1, int(SPIKE_SHARE * n)), replace=False))
    outputs = rng.integers(0, len(reactor.OUTPUTS), rows.size)
    x = fleet[list(reactor.OUTPUTS)].to_numpy().copy()
    sigma = np.array(list(reactor.NOISE.values()))
    x[rows, outputs] += (
        rng.choice([-1.0, 1.0], rows.size) * SPIKE_SIGMA * sigma[outputs]
    )
    out = fleet.copy()
    out[list(reactor.OUTPUTS)] = x
    return out, rows


def run(seeds: int, units: int, phi: float = PHI) -> list[dict]:
    jax_config()
    model, cfg = reactor.reactor_model(), LoopConfig()
    rows = []
    for seed in range(seeds):
        fleet = reactor.make_fleet(seed, units=units, rows=ROWS, phi=phi)
        near, first = _changes(fleet)
        left, sec = _screen(model, fleet, cfg)
        spiked, planted = _spiked(fleet, seed)
        left_s, sec_s = _screen(model, spiked, cfg)
        found = np.zeros(len(fleet), bool)
        found[planted] = True
        rows.append({
            "seed": seed, "phi": phi, "rows": len(fleet), "set_point_changes": int(
                np.sum(np.any(np.diff(fleet[list(reactor.CONDITIONS)].to_numpy(),
                                      axis=0), 1) & ~first[1:])),
            "clean_left_out": int(left.sum()),
            "clean_near_change": int((left & near).sum()),
            "clean_first_rows": int((left & first).sum()),
            "clean_rows": np.flatnonzero(left).tolist(),
            "at_truth_flagged": _at_truth(fleet, cfg),
            "spikes": int(planted.size),
            "spikes_found": int(left_s[planted].sum()),
            "spiked_other_left_out": int((left_s & ~found).sum()),
            "seconds": [round(sec, 2), round(sec_s, 2)],
        })  # fmt: skip
        print(json.dumps(rows[-1]), flush=True)
    return rows


def jax_config():
    import jax

    jax.config.update("jax_enable_x64", True)  # the diagnosis needs float64


def markdown(results: dict) -> str:
    lines = [
        "# Transients are not outliers (issue 43 item 4)",
        "",
        f"The reactor (`experiments/reactor.py`), units of {ROWS} samples, set-point "
        "changes every 10-40 samples, AR(1) noise (coefficient in the table), the "
        "noise estimated; the "
        "diagnosis's screening (`jaxcal.diagnosis.data.cleaning.drop_outliers`). `near "
        f"change`: within {AROUND} rows of a set-point change; `first`: a unit's "
        f"first row; spikes: {SPIKE_SIGMA:g} sensor stds on one output of "
        f"{100 * SPIKE_SHARE:g} % of the rows. `at truth`: the neighbour test on the "
        "residual at the true parameters (the premise: 0).",
        "",
        "Command: `python experiments/transients.py seeds=4 units=6 label=after` "
        "(`label=before` with `PYTHONPATH` on the previous commit's package).",
        "",
        "| code | AR(1) | seed | rows | changes | left out (clean) | near change "
        "| first | at truth | spikes found | other rows left out (spiked) | s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label in results:  # in the order they were run
        for r in results[label]["seeds"]:
            lines.append(
                f"| {label} | {r['phi']:g} | {r['seed']} | {r['rows']} | "
                f"{r['set_point_changes']} | "
                f"{r['clean_left_out']} | {r['clean_near_change']} | "
                f"{r['clean_first_rows']} | {r['at_truth_flagged']} | "
                f"{r['spikes_found']}/{r['spikes']} | {r['spiked_other_left_out']} | "
                f"{r['seconds'][0]:.1f} |"
            )
    lines.append("")
    for label in results:  # in the order they were run
        seeds = results[label]["seeds"]
        total = sum(r["rows"] for r in seeds)
        left = sum(r["clean_left_out"] for r in seeds)
        lines.append(
            f"- **{label}** ({results[label]['commit']}): {left} of {total} clean rows "
            f"left out ({100 * left / total:.2f} %), "
            f"{sum(r['clean_near_change'] for r in seeds)} near a set-point change; "
            f"spikes found {sum(r['spikes_found'] for r in seeds)}/"
            f"{sum(r['spikes'] for r in seeds)}, other rows left out with them "
            f"{sum(r['spiked_other_left_out'] for r in seeds)}."
        )
    return "\n".join(lines) + "\n"


def main(argv) -> None:
    args = dict(a.split("=", 1) for a in argv)
    out = args.get("out", os.path.join(os.path.dirname(HERE), "results", "loop"))
    label = args.get("label", "after")
    seeds = run(
        int(args.get("seeds", 4)),
        int(args.get("units", 6)),
        float(args.get("phi", PHI)),
    )
    path = os.path.join(out, "transients.json")
    results = {}
    if os.path.exists(path):
        with open(path) as f:
            results = json.load(f)
    results[label] = {
        "commit": args.get("commit", "working tree"),
        "package": os.path.dirname(jaxcal.__file__),
        "seeds": seeds,
    }
    write_atomic(path, json.dumps(results, indent=1) + "\n")
    write_atomic(os.path.join(out, "transients.md"), markdown(results))
    print(f"wrote {path} and transients.md")


if __name__ == "__main__":
    main(sys.argv[1:])
