"""Close the loop on the real NASA C-MAPSS training files FD001 and FD002.

Calibrates ``HPC_eff_mod, HPC_flow_mod`` of the ``cmapss`` engine (the fault mode of
FD001 / FD002 is HPC degradation) per unit as splines in cycle, estimates the sensor
noise from the residual, traces the residual to the effect library, falls back to a
discrepancy delta(w) where the library does not explain it, and writes one result page
per file (``<out>/<FD>/report.md``, ``report.json``, figures) plus ``<out>/README.md``
with what the loop found, its size and the error before and after.

C-MAPSS has one row per flight (no within-flight time), so ``tau`` and the spline basis
run over cycles. Nf, NRf, Nf_dmd and PCNfR_dmd are set by the controller and s11 / s12
are not physical (they are extras of the loader), so none of them enters the residual;
sensors whose readings are constant or rounded too coarsely are dropped and listed.

Usage::

    python experiments/loop_cmapss.py [files=FD001,FD002] [max_rows=0]
        [data_dir=/work/shared/data/cmapss] [out=results/loop/cmapss]

``files`` also takes paths to any C-MAPSS text file (``files=/x/train_FD003.txt``).
Every page lists, per added effect, the units that carry it (Holm-corrected z-test),
their sizes and onsets, and the plausibility flags of the verdict.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

import numpy as np

from jaxcal.cache import enable_compilation_cache
from jaxcal.data.readers import read_dataset
from jaxcal.diagnosis.pipeline import LoopConfig, diagnose
from jaxcal.diagnosis.report.markdown import effect_line
from jaxcal.diagnosis.report.write import write_report, write_text
from jaxcal.models import load
from jaxcal.precision import enable_x64
from jaxcal.settings import config_to_dict, parse_overrides

DEFAULT_DIR = os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data", "cmapss"
)


@dataclasses.dataclass(frozen=True)
class CmapssLoopConfig:
    # train_<FD>.txt files in data_dir, or paths to any C-MAPSS .txt files
    files: tuple[str, ...] = ("FD001", "FD002")
    data_dir: str = os.path.normpath(DEFAULT_DIR)  # folder of the NASA text files
    declared: tuple[str, ...] = ("HPC_eff_mod", "HPC_flow_mod")
    engine: str = "cmapss"
    max_rows: int = 0  # subsample to about this many rows (0: every row)
    knots: int = 6  # spline functions per unit and declared modifier
    out: str = "results/loop/cmapss"


def _per_unit(rep: dict, length: dict) -> list[str]:
    """One bullet per added effect: who carries it, how much, from when.

    ``length``: unit id -> cycles in its record. The correlation of the per-unit size
    with the record length and the onset as a share of the record tell a fault that
    ends every life at a similar level (rate ~ 1 / life, late onset) from a sensor
    fault (rate independent of life).
    """
    rows = []
    for e in rep["identified"]:
        units = e["units"]
        car = [u for u in units if u["carries"]]
        ids = ", ".join(str(u["unit"]) for u in car[:40])
        more = f" and {len(car) - 40} more" if len(car) > 40 else ""
        onsets = [u["onset"] for u in car if u["onset"] is not None]
        onset = (
            f"; onset cycle median {np.median(onsets):.0f} (range "
            f"{min(onsets):.0f}-{max(onsets):.0f})"
            if onsets
            else ""
        )
        sizes = np.array([u["size"] for u in car])
        size_txt = (
            f"; size in the carriers median {np.median(sizes):.4g}, range "
            f"[{sizes.min():.4g}, {sizes.max():.4g}] {e['unit']}"
            if sizes.size
            else ""
        )
        others = "–" if e["size_others"] is None else f"{e['size_others']:.4g}"
        every = np.array([u["size"] for u in units], float)
        life = np.array([length[u["unit"]] for u in units], float)
        ok = np.isfinite(every)
        corr = (
            f"; correlation of the per-unit size with the record length "
            f"{np.corrcoef(every[ok], life[ok])[0, 1]:+.2f}"
            if ok.sum() > 2 and np.ptp(every[ok]) > 0 and np.ptp(life[ok]) > 0
            else ""
        )
        share = [u["onset"] / length[u["unit"]] for u in car if u["onset"] is not None]
        share_txt = (
            f"; onset at {np.median(share):.0%} of the record (median)" if share else ""
        )
        rows.append(
            f"- Per unit, {e['name']}: carried by {len(car)} of {len(units)} units "
            f"({e['unit_test']}){size_txt}{onset}{share_txt}; mean in the others "
            f"{others}{corr}." + (f" Carriers: {ids}{more}." if car else "")
        )
    return rows


def _line(name: str, rep: dict, seconds: float, length: dict) -> list[str]:
    b, a = rep["before"], rep["after"]
    num_units = rep["data"]["units"]
    found = (
        "; ".join(effect_line(e, num_units) for e in rep["identified"])
        or "no library effect"
    )
    flags = [f"{f['flag']} ({f['subject']}): {f['detail']}" for f in rep["flags"]]
    disc = rep["discrepancy"] or []
    disc_txt = (
        "; ".join(
            f"{s['sensor']} (std {s['amplitude_units']:.3g}, "
            f"mean {s['mean_units']:.3g}; "
            + ", ".join(
                f"{k} {v:.2f}"
                for k, v in sorted(s["dependence"].items(), key=lambda kv: -kv[1])[:2]
            )
            + ")"
            for s in disc
        )
        or "none"
    )
    rows = [
        f"## {name}",
        "",
        f"{rep['data']['rows']} rows, {rep['data']['units']} units, sensors "
        f"{', '.join(rep['data']['sensors'])} ({seconds / 60:.1f} min). "
        f"[Full page]({name}/report.md).",
        "",
        f"- Verdict: **{rep['verdict']}**"
        f"{' — FLAGGED' if flags else ' (no plausibility flag)'}; added: "
        f"{', '.join(rep['added']) or 'nothing'}.",
        f"- Library effect: {found}.",
        *_per_unit(rep, length),
        *[f"- Flag: {f}." for f in flags],
        f"- Confounded with it: {', '.join(rep['confounded']) or 'none'}.",
        f"- Discrepancy delta(w): {disc_txt}.",
        f"- Mean tracking RMSE {b['mean_tracking_rmse_norm']:.3f} -> "
        f"{a['mean_tracking_rmse_norm']:.3f} noise std; white sensors (Ljung–Box "
        f"p > 0.01) {b['whiteness']:.2f} -> {a['whiteness']:.2f}.",
        "",
        "| sensor | noise std | RMSE before | after |",
        "|---|---|---|---|",
    ]
    for s in rep["data"]["sensors"]:
        rows.append(
            f"| {s} | {rep['data']['noise_std'][s]:.4g} | "
            f"{b['tracking_rmse'][s]:.4g} | {a['tracking_rmse'][s]:.4g} |"
        )
    top = rep["ranking"][:5]
    rows += [
        "",
        "Top of the ranking against the declared-only residual: "
        + "; ".join(f"{e['name']} (delta BIC {e['delta_bic']:.0f})" for e in top)
        + ".",
        "",
    ]
    return rows


def _path(data_dir: str, entry: str) -> str:
    """``FD003`` -> ``<data_dir>/train_FD003.txt``; a ``.txt`` path is used as is."""
    if entry.endswith(".txt"):
        return entry
    return os.path.join(data_dir, f"train_{entry}.txt")


def _label(entry: str) -> str:
    """The page name of a file entry (``FD003``, or a path's file stem)."""
    return (
        os.path.splitext(os.path.basename(entry))[0]
        if entry.endswith(".txt")
        else entry
    )


def main(argv: list[str]) -> int:
    try:
        cfg = parse_overrides(argv, CmapssLoopConfig())
        paths = {_label(fd): _path(cfg.data_dir, fd) for fd in cfg.files}
        missing = [p for p in paths.values() if not os.path.isfile(p)]
        if missing:
            raise FileNotFoundError(
                f"C-MAPSS file(s) not found: {', '.join(missing)} (set data_dir=)"
            )
    except (ValueError, FileNotFoundError) as err:
        print(f"loop_cmapss: {err}", file=sys.stderr)
        return 2
    enable_x64()
    enable_compilation_cache()
    model = load(cfg.engine)
    loop_cfg = LoopConfig(knots=cfg.knots)
    command = "python experiments/loop_cmapss.py " + " ".join(argv)
    lines = [
        "# Closing the loop on NASA C-MAPSS ("
        + ", ".join(os.path.basename(p) for p in paths.values())
        + ")",
        "",
        f"Command: `{command.strip()}`. Engine `{cfg.engine}` with its current design "
        f"constants; declared {', '.join(cfg.declared)} per unit ({cfg.knots} cubic "
        "B-spline functions in cycle); noise estimated from the residual: an AR(p) "
        "colour per output and its level (nearest-neighbour differences of the "
        "prewhitened residual in (w, cycle)), every test on the prewhitened "
        "residual; effects fleet-wide or in the units that carry them, steps with "
        "their onsets.",
        "",
    ]
    for fd, path in paths.items():
        start = time.time()
        data = read_dataset(path, model)
        res = diagnose(
            data, model, cfg.declared, loop_cfg, max_rows=cfg.max_rows or None,
            progress=True,
        )  # fmt: skip
        seconds = time.time() - start
        config = {
            **config_to_dict(cfg),
            "loop": config_to_dict(loop_cfg),
            "seconds": seconds,
        }
        rep = write_report(
            os.path.join(cfg.out, fd),
            res,
            source=path,
            model=cfg.engine,
            config=config,
            base_spec=cfg.engine,
        )
        d = res.data
        length = dict(
            zip(
                d.unit_ids.tolist(),
                (d.cycle[d.starts[1:] - 1] - d.cycle[d.starts[:-1]] + 1).tolist(),
                strict=True,
            )
        )
        lines += _line(fd, rep, seconds, length)
        print(
            f"{fd}: verdict {rep['verdict']}, added {rep['added']}, mean tracking "
            f"RMSE {rep['before']['mean_tracking_rmse_norm']:.3f} -> "
            f"{rep['after']['mean_tracking_rmse_norm']:.3f} ({seconds / 60:.1f} min)",
            flush=True,
        )
    write_text(os.path.join(cfg.out, "README.md"), "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
