"""The extended model of an effect some units carry, before and after (issue 43 item 3).

The newcomer's reactor (``experiments/reactor.py``): 6 units of 500 samples, a +1.5 K
step of the temperature sensor from sample 300 in units 1 and 3. The diagnosis
(``python -m jaxcal.diagnose``, the declared ``activity``, ``UA`` and ``dH``) exports
``extended_model.json``; the UKF (``jaxcal.calibrate``, noise estimated, as a new
user would run it) then calibrates the fleet with

* ``base``: the base model, the declared parameters;
* ``every unit``: the exported model with the offset tracked in every unit (what the
  export did before: the file with its ``units`` removed);
* ``carriers``: the exported model as written, the offset calibrated in the units the
  verdict names and held at 0 in the others (:mod:`jaxcal.calibrators.carriers`).

Per unit: each declared parameter's error at the unit's last sample and its RMSE
from the step on, and the tracked offset at the last sample with its reported std
against the truth (1.5 K in a carrier, 0 elsewhere).

Usage::

    python experiments/per_unit_extension.py [seed=0] [out=results/loop]

Writes ``<out>/per_unit_extension.json`` and ``.md``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import reactor  # noqa: E402

import jaxcal  # noqa: E402
from jaxcal.models.extended import build_extended  # noqa: E402
from jaxcal.runs.atomic import write_atomic  # noqa: E402

DECLARED = ("activity", "UA", "dH")
CARRIERS, STEP, ONSET = (1, 3), 1.5, 300
OFFSET = "T_offset"


def _diagnose(data_path: str, out: str) -> dict:
    """Run the diagnosis command line; its report.json."""
    spec = f"{os.path.join(HERE, 'reactor.py')}:reactor_model"
    cmd = [
        sys.executable, "-m", "jaxcal.diagnose", f"model={spec}", f"data={data_path}",
        f"calibrate={','.join(DECLARED)}", f"out={out}",
    ]  # fmt: skip
    subprocess.run(cmd, check=True, cwd=os.path.dirname(HERE))
    with open(os.path.join(out, "report.json")) as f:
        return json.load(f)


def _calibrate(model, fleet, theta=None, noise=None):
    # the true parameters the model does not have (E_scale, held) are no column of it
    known = {*model.condition_names, *model.output_names, *model.parameter_names,
             "unit", "time"}  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        table = fleet.drop(columns=[c for c in fleet if c not in known])
        res = jaxcal.calibrate(
            model, table, "ukf", theta=theta, noise=noise, progress=False
        )
    return res, [str(w.message) for w in caught]


def _per_unit(res, fleet) -> dict:
    """``{unit: {param: {end, rmse}}, offset: {est, std}}``."""
    out = {}
    for u in sorted(set(fleet["unit"])):
        rows = np.flatnonzero(res.unit == u)
        late = rows[res.time[rows] >= ONSET]
        entry = {}
        for p in DECLARED:
            j, truth = res.theta_names.index(p), fleet[p].to_numpy()
            entry[p] = {
                "end": float(abs(res.theta[rows[-1], j] - truth[rows[-1]])),
                "rmse": float(
                    np.sqrt(np.mean((res.theta[late, j] - truth[late]) ** 2))
                ),
            }
        if OFFSET in res.theta_names:
            j = res.theta_names.index(OFFSET)
            std = None if res.theta_std is None else res.theta_std[rows[-1], j]
            entry[OFFSET] = {
                "est": float(res.theta[rows[-1], j]),
                "std": None if std is None or not np.isfinite(std) else float(std),
                "truth": STEP if u in CARRIERS else 0.0,
            }
        out[int(u)] = entry
    return out


def _offset_of(rep: dict, u: int) -> tuple[float, float]:
    """The carriers' run's offset and std at unit ``u``'s last sample (noise given)."""
    e = rep["noise_given"]["runs"]["carriers"]["units"][str(u)][OFFSET]
    return e["est"], e["std"]


def _ratios(r: dict) -> str:
    return ", ".join(
        f"{k} {r[k + ', end']:.3f} ({r[k + ', rmse']:.3f})"
        for k in ("every unit", "carriers")
    )


def _markdown(rep: dict) -> str:
    runs = rep["runs"]
    units = sorted(runs["base"]["units"], key=int)
    lines = [
        "# The extended model of an effect some units carry (issue 43 item 3)",
        "",
        f"Made by `python experiments/per_unit_extension.py seed={rep['seed']}` "
        f"({rep['seconds']:.0f} s). The reactor (`experiments/reactor.py`), 6 units "
        f"of 500 samples, a +{STEP} K temperature-sensor step from sample {ONSET} in "
        f"units {list(CARRIERS)}. The diagnosis (declared {', '.join(DECLARED)}) "
        f"said `{rep['verdict']}` and exported `{OFFSET}` for units "
        f"{rep['exported_units']}. The UKF (`jaxcal.calibrate`, noise estimated) "
        "with the base model, the exported model with the offset tracked in every "
        "unit (the export before), and the exported model as written (the offset "
        "calibrated in the carriers, held at 0 elsewhere).",
        "",
        "## Declared parameters: error at the unit's last sample "
        "(RMSE from the step on)",
        "",
        "| unit | carrier | parameter | base | every unit | carriers |",
        "|---|---|---|---|---|---|",
    ]
    for u in units:
        for p in DECLARED:
            cells = [
                f"{runs[k]['units'][u][p]['end']:.4f} "
                f"({runs[k]['units'][u][p]['rmse']:.4f})"
                for k in ("base", "every unit", "carriers")
            ]
            carrier = "yes" if int(u) in CARRIERS else ""
            lines.append(f"| {u} | {carrier} | {p} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Clean units, mean over units and parameters of the error (at the last "
        "sample; RMSE from the step on) relative to the base model's: "
        + _ratios(rep["clean_ratio"])
        + ". The carriers' run estimates the noise per group of units (the note "
        "below), the base run over all six, whose carriers misfit: the clean units' "
        "small differences from the base run come from there. With the true noise "
        "given (`noise=`): "
        + _ratios(rep["noise_given"]["clean_ratio"])
        + "; the carriers' offset "
        + ", ".join(
            "unit {} {:+.3f} +- {:.3f} K".format(u, *_offset_of(rep, u))
            for u in CARRIERS
        )
        + ".",
        "",
        f"## The tracked offset `{OFFSET}` at the unit's last sample (K)",
        "",
        "| unit | truth | every unit: est +- std | carriers: est +- std | "
        "carriers: error / std |",
        "|---|---|---|---|---|",
    ]

    def pm(e):
        return f"{e['est']:+.3f} +- " + (
            "n/a" if e["std"] is None else f"{e['std']:.3f}"
        )

    for u in units:
        a, b = (
            runs["every unit"]["units"][u][OFFSET],
            runs["carriers"]["units"][u][OFFSET],
        )
        z = (
            "held (std 0)" if b["std"] == 0.0
            else "n/a" if b["std"] is None
            else f"{abs(b['est'] - b['truth']) / b['std']:.2f}"
        )  # fmt: skip
        lines.append(f"| {u} | {b['truth']:.1f} | {pm(a)} | {pm(b)} | {z} |")
    lines += ["", "Notes of the carriers' run:", ""]
    lines += [f"- {n}" for n in rep["runs"]["carriers"]["notes"]]
    return "\n".join(lines) + "\n"


def main(argv) -> None:
    args = dict(a.split("=", 1) for a in argv)
    seed, out = int(args.get("seed", 0)), args.get("out", "results/loop")
    start = time.perf_counter()
    fleet = reactor.make_fleet(
        seed, units=6, rows=500, bias=STEP, bias_units=CARRIERS, bias_from=ONSET
    )
    model = reactor.reactor_model()
    with tempfile.TemporaryDirectory() as tmp:
        data_path = os.path.join(tmp, "reactor.csv")
        fleet.to_csv(data_path, index=False)
        report = _diagnose(data_path, os.path.join(tmp, "diag"))
        ext_path = os.path.join(tmp, "diag", "extended_model.json")
        with open(ext_path) as f:
            spec = json.load(f)
    added = {a["name"]: a for a in spec["added"]}
    if OFFSET not in added:
        raise SystemExit(f"the diagnosis exported {list(added)}, not {OFFSET}")
    from jaxcal.models.extended import Added

    adds = [Added(**a) for a in spec["added"]]
    exported = build_extended(model, spec["declared"], adds)
    every = build_extended(
        model, spec["declared"], [a._replace(units=None) for a in adds]
    )
    clean = [str(u) for u in sorted(set(fleet["unit"])) if u not in CARRIERS]

    def calibrated(noise):
        runs = {}
        for name, mdl, theta in (
            ("base", model, list(DECLARED)), ("every unit", every, None),
            ("carriers", exported, None),
        ):  # fmt: skip
            res, notes = _calibrate(mdl, fleet, theta, noise)
            units = {str(k): v for k, v in _per_unit(res, fleet).items()}
            runs[name] = {"units": units, "notes": notes}
        return runs

    def ratios(runs):
        def clean_error(run, key):
            return np.mean(
                [runs[run]["units"][u][p][key] for u in clean for p in DECLARED]
            )

        return {
            f"{k}, {key}": float(clean_error(k, key) / clean_error("base", key))
            for k in ("every unit", "carriers") for key in ("end", "rmse")
        }  # fmt: skip

    runs, given = calibrated(None), calibrated(reactor.NOISE)

    rep = {
        "seed": seed,
        "verdict": report["verdict"],
        "identified": [i["name"] for i in report["identified"]],
        "exported_units": added[OFFSET].get("units"),
        "runs": runs,
        "clean_ratio": ratios(runs),
        "noise_given": {"runs": given, "clean_ratio": ratios(given)},
        "seconds": time.perf_counter() - start,
    }
    os.makedirs(out, exist_ok=True)
    write_atomic(
        os.path.join(out, "per_unit_extension.json"), json.dumps(rep, indent=1) + "\n"
    )
    write_atomic(os.path.join(out, "per_unit_extension.md"), _markdown(rep))
    print(_markdown(rep))


if __name__ == "__main__":
    main(sys.argv[1:])
