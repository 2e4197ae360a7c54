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
  verdict names and held at 0 in the others (:mod:`jaxcal.calibrators.front.carriers`).

Per unit: each declared parameter's error at the unit's last sample and its RMSE
from the step on, and the tracked offset at the last sample with its reported std
against the truth (1.5 K in a carrier, 0 elsewhere).

The fleet command line (``python -m jaxcal.fleet``, the UKF, the true noise given: it
estimates none) runs the same three on the same fleet, the exported model's offset
held in the clean units as ``jaxcal.calibrate`` holds it (:mod:`jaxcal.fleet.per_unit`),
and the exported model once more on two ``jax.distributed`` processes (the file
compared with one process's).

Usage::

    python experiments/per_unit_extension.py [seed=0] [out=results/loop]

Writes ``<out>/per_unit_extension.json`` and ``.md``.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import types
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


def _fleet_cli(args: list[str], out: str, processes: int = 1) -> tuple[object, float]:
    """Run ``python -m jaxcal.fleet args out=out`` (on ``processes`` processes of
    one CPU device each); ``(its results as a calibration result, wall seconds)``:
    the file's rows in the data's row order (its ``row`` column)."""
    from jaxcal.fleet.results import read_results

    cmd = [sys.executable, "-m", "jaxcal.fleet", *args, f"out={out}"]
    start = time.perf_counter()
    if processes == 1:
        subprocess.run(cmd, check=True, cwd=os.path.dirname(HERE))
    else:
        with socket.socket() as sock:  # a free port for the coordinator
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        cluster = ["--coordinator", f"127.0.0.1:{port}", "--num-processes",
                   str(processes), "--local-devices", "1"]  # fmt: skip
        procs = [
            subprocess.Popen(
                [*cmd, *cluster, "--process-id", str(i)], cwd=os.path.dirname(HERE)
            )  # fmt: skip
            for i in range(processes)
        ]
        if any(p.wait() != 0 for p in procs):
            raise SystemExit(f"{' '.join(cmd)}: a process failed")
    seconds = time.perf_counter() - start
    arrays, attrs = read_results(out)
    order = np.argsort(arrays["row"], kind="stable")
    res = types.SimpleNamespace(
        unit=arrays["unit"][order], time=arrays["time"][order],
        theta=arrays["theta"][order], theta_std=arrays["aux_theta_std"][order],
        theta_names=tuple(attrs["theta_names"]), notes=list(attrs.get("notes", [])),
        arrays=arrays,
    )  # fmt: skip
    return res, seconds


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
    lines += _fleet_markdown(rep["fleet_cli"], units, pm)
    return "\n".join(lines) + "\n"


def _fleet_markdown(fleet: dict, units, pm) -> list[str]:
    runs, diff = fleet["runs"], fleet["vs_calibrate"]
    lines = [
        "",
        "## The fleet command line (`python -m jaxcal.fleet`)",
        "",
        "The same fleet, the same three models, by the fleet command line (the UKF "
        "with the true noise given: the command line estimates none). The exported "
        "model, as run here (`<diagnosis>`: the diagnosis's report folder; "
        "`reactor.csv`: the fleet with the model's columns only):",
        "",
        "```bash",
        fleet["command"],
        "```",
        "",
        "and `model=experiments/reactor.py:reactor_model theta=activity,UA,dH` "
        "(base), the exported file with its `units` removed (every unit). Wall "
        "time, each a fresh process (model load included; the compiled programs "
        "may come from the on-disk cache of an earlier run): "
        + ", ".join(f"{k} {runs[k]['seconds']:.1f} s" for k in runs)
        + ".",
        "",
        "Clean units, mean over units and parameters of the error (at the last "
        "sample; RMSE from the step on) relative to the fleet command line's base "
        "run: " + _ratios(fleet["clean_ratio"]) + ". (`jaxcal.calibrate` with the "
        "noise given: " + _ratios(fleet["calibrate_clean_ratio"]) + ".) Against "
        "`jaxcal.calibrate` with the noise given, the largest difference of a "
        "declared parameter's error (at the last sample or RMSE) in the clean units: "
        + ", ".join(f"{k} {diff[k + ', clean']:.2g}" for k in runs)
        + "; in the carriers: "
        + ", ".join(f"{k} {diff[k + ', carriers']:.2g}" for k in runs)
        + " (`jaxcal.calibrate` screens and skips 2 outlier rows of the carriers, "
        "the command line none).",
        "",
        "| unit | truth | every unit: est +- std | carriers: est +- std | "
        "carriers: error / std |",
        "|---|---|---|---|---|",
    ]
    for u in units:
        a, b = (runs[k]["units"][u][OFFSET] for k in ("every unit", "carriers"))
        z = (
            "held (std 0)" if b["std"] == 0.0
            else f"{abs(b['est'] - b['truth']) / b['std']:.2f}"
        )  # fmt: skip
        lines.append(f"| {u} | {b['truth']:.1f} | {pm(a)} | {pm(b)} | {z} |")
    held = fleet["held"]
    two = fleet["two_processes"]
    lines += [
        "",
        f"In the clean units the offset column is {held['max_abs_offset']:g} and its "
        f"std {held['max_std']:g} at every row ({held['rows']} rows). The file's "
        f"notes: {'; '.join(runs['carriers']['notes'])}.",
        "",
        "On two `jax.distributed` processes (`--coordinator 127.0.0.1:PORT "
        "--num-processes 2 --process-id I --local-devices 1`, "
        f"{two['seconds']:.1f} s): the file "
        + (
            "equal to one process's, bit for bit"
            if two["max_abs_diff"] == 0.0
            else f"within {two['max_abs_diff']:.1g} of one process's"
        )
        + f" ({two['columns']} columns, {two['rows']} rows).",
    ]
    return lines


def _fleet_runs(tmp: str, fleet, spec: dict, model) -> dict:
    """The fleet command line's base, every-unit and carriers runs (and the
    carriers' on two processes) on ``fleet``; their per-unit numbers."""
    diag = os.path.join(tmp, "diag")
    every_path = os.path.join(diag, "every_unit.json")  # beside it: the same base
    with open(every_path, "w") as f:
        json.dump({**spec, "added": [{**a, "units": None} for a in spec["added"]]}, f)
    known = [*model.condition_names, *model.output_names, "unit", "time", *DECLARED]
    data_path = os.path.join(tmp, "reactor_model_columns.csv")
    fleet[known].to_csv(data_path, index=False)  # the true E_scale: no model's column
    noise = "noise=" + ",".join(f"{k}:{v}" for k, v in reactor.NOISE.items())
    common = [f"data={data_path}", "method=ukf", noise, "trust_code=true"]
    base_spec = f"{os.path.join(HERE, 'reactor.py')}:reactor_model"
    models = {
        "base": [f"model={base_spec}", f"theta={','.join(DECLARED)}"],
        "every unit": [f"model={every_path}"],
        "carriers": [f"model={os.path.join(diag, 'extended_model.json')}"],
    }
    runs, results = {}, {}
    for name, args in models.items():
        res, seconds = _fleet_cli([*args, *common], os.path.join(tmp, "fleet.h5"))
        units = {str(k): v for k, v in _per_unit(res, fleet).items()}
        runs[name] = {"units": units, "notes": res.notes, "seconds": seconds}
        results[name] = res
    carriers = results["carriers"]
    clean = ~np.isin(carriers.unit, CARRIERS)
    j = carriers.theta_names.index(OFFSET)
    two, seconds = _fleet_cli(
        [*models["carriers"], *common], os.path.join(tmp, "fleet2.h5"), processes=2
    )
    one_file, two_file = carriers.arrays, two.arrays
    if sorted(one_file) != sorted(two_file):
        raise SystemExit("two processes wrote other columns than one")
    command = (
        "python -m jaxcal.fleet model=<diagnosis>/extended_model.json "
        "data=reactor.csv method=ukf "
        + noise + " trust_code=true out=fleet.h5"
    )  # fmt: skip
    return {
        "command": command,
        "runs": runs,
        "held": {
            "rows": int(clean.sum()),
            "max_abs_offset": float(np.abs(carriers.theta[clean, j]).max()),
            "max_std": float(np.abs(carriers.theta_std[clean, j]).max()),
        },
        "two_processes": {
            "seconds": seconds,
            "columns": len(one_file),
            "rows": int(one_file["theta"].shape[0]),
            "max_abs_diff": float(
                max(
                    np.abs(two_file[k].astype(float) - one_file[k].astype(float)).max()
                    for k in one_file
                )
            ),  # fmt: skip
        },
    }


def _differences(fleet_runs: dict, given: dict, clean: list[str]) -> dict:
    """The largest difference of the declared parameters' errors (at the last
    sample, RMSE from the step on) between the command line's runs and
    ``jaxcal.calibrate``'s with the noise given, over the clean units and the
    carriers."""
    groups = {"clean": clean, "carriers": [str(u) for u in CARRIERS]}
    return {
        f"{run}, {group}": float(
            max(
                abs(
                    fleet_runs[run]["units"][u][p][key] - given[run]["units"][u][p][key]
                )
                for u in units
                for p in DECLARED
                for key in ("end", "rmse")
            )
        )  # fmt: skip
        for run in ("base", "every unit", "carriers")
        for group, units in groups.items()
    }


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
        fleet_cli = _fleet_runs(tmp, fleet, spec, model)
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
    fleet_cli["clean_ratio"] = ratios(fleet_cli["runs"])
    fleet_cli["calibrate_clean_ratio"] = ratios(given)
    fleet_cli["vs_calibrate"] = _differences(fleet_cli["runs"], given, clean)

    rep = {
        "seed": seed,
        "verdict": report["verdict"],
        "identified": [i["name"] for i in report["identified"]],
        "exported_units": added[OFFSET].get("units"),
        "runs": runs,
        "clean_ratio": ratios(runs),
        "noise_given": {"runs": given, "clean_ratio": ratios(given)},
        "fleet_cli": fleet_cli,
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
