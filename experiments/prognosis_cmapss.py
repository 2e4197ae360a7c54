"""Remaining useful life on NASA C-MAPSS FD001 / FD002, scored against NASA's truth.

For each file: the ``cmapss`` engine's HPC and fan efficiency and flow
(:data:`~jaxcal.models.turbofan.model.PROGNOSIS_THETA`) are calibrated by the UKF
on the run-to-failure units (``train_FD00x.txt``) and on the test units
(``test_FD00x.txt``); the fleet's degradation and failure boundary are learned from the
training units' ends, and each test unit's RUL is predicted with a 90 % interval
(:func:`jaxcal.prognosis.prognose`) and scored against ``RUL_FD00x.txt``. Writes
``<out>/<FD>/`` (the command line's folder: ``rul.csv``, ``report.md``/``.json``, the
figures) and ``<out>/README.md``: the table, beside the published deep networks'.

Usage::

    python experiments/prognosis_cmapss.py [files=FD001,FD002]
        [data_dir=/work/shared/data/cmapss] [out=results/prognosis]
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

import numpy as np

from jaxcal.cache import enable_compilation_cache
from jaxcal.models.turbofan.model import PROGNOSIS_OUTPUTS, PROGNOSIS_THETA
from jaxcal.precision import enable_x64
from jaxcal.prognosis import PrognosisConfig, prognose, read_truth, score
from jaxcal.prognosis.report import write_prognosis
from jaxcal.settings import config_to_dict, parse_overrides

DEFAULT_DIR = os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data", "cmapss"
)
# Published test-set RMSEs of deep networks, as issue 45 quotes them (cycles; their
# targets are capped at 125-130 cycles, and none gives an interval).
PUBLISHED = (
    ("deep network A (as quoted in issue 45)", 10.97, 16.81),
    ("deep network B (as quoted in issue 45)", 12.31, 12.55),
)
# The literature's piecewise-linear target caps the RUL at 125 cycles. Papers differ on
# whether the test truth is capped too; both capped RMSEs are shown beside ours only to
# make the convention's effect visible (NASA's truth reaches 145 cycles on FD001, 194
# on FD002: 11 and 57 test units above the cap).
LITERATURE_CAP = 125.0


@dataclasses.dataclass(frozen=True)
class PrognosisCmapssConfig:
    files: tuple[str, ...] = ("FD001", "FD002")
    data_dir: str = os.path.normpath(DEFAULT_DIR)
    method: str = "ukf"
    seed: int = 0
    out: str = "results/prognosis"
    all_figures: bool = False  # a figure of every test unit (else a selection)


def _shown(units, truth, rul) -> list:
    """The units drawn for the committed pages (every unit's figure is ~35 kB): one
    per tenth of the true RULs and the five worst predictions."""
    by_truth = np.argsort(truth, kind="stable")
    spread = by_truth[np.linspace(0, by_truth.size - 1, 10).round().astype(int)]
    worst = np.argsort(-np.abs(rul - truth), kind="stable")[:5]
    return [units[i] for i in sorted(set(spread) | set(worst))]


def _paths(data_dir: str, fd: str) -> tuple[str, str, str]:
    return tuple(
        os.path.join(data_dir, f"{kind}_{fd}.txt") for kind in ("train", "test", "RUL")
    )


def _run(cfg: PrognosisCmapssConfig, fd: str) -> dict:
    train, test, truth_path = _paths(cfg.data_dir, fd)
    start = time.perf_counter()
    result = prognose(
        "cmapss", train, test, theta=PROGNOSIS_THETA, outputs=PROGNOSIS_OUTPUTS,
        config=PrognosisConfig(method=cfg.method, seed=cfg.seed),
    )  # fmt: skip
    seconds = time.perf_counter() - start
    pred = result.prediction
    truth = read_truth(truth_path, pred.unit.size)
    scores = score(pred.rul, pred.rul_low, pred.rul_high, truth)
    capped = np.minimum(pred.rul, LITERATURE_CAP)
    scores["rmse_capped_125"] = float(np.sqrt(np.mean((capped - truth) ** 2)))
    both = capped - np.minimum(truth, LITERATURE_CAP)
    scores["rmse_both_capped_125"] = float(np.sqrt(np.mean(both**2)))
    scores["seconds"] = seconds
    scores["drivers"] = {n: int(pred.driver.count(n)) for n in set(pred.driver)}
    write_prognosis(
        os.path.join(cfg.out, fd), result, truth=truth,
        source={"train": train, "test": test, "truth": truth_path},
        config={**config_to_dict(cfg), "file": fd},
        unit_figures=None if cfg.all_figures else _shown(pred.unit, truth, pred.rul),
    )  # fmt: skip
    return scores


def _readme(cfg: PrognosisCmapssConfig, rows: dict, argv: list[str]) -> str:
    lines = [
        "# Remaining useful life on NASA C-MAPSS, from the calibrated twin",
        "",
        "Command: `"
        + f"python experiments/prognosis_cmapss.py {' '.join(argv)}".rstrip()
        + "` (one folder per file below: `rul.csv`, `report.md`, figures; the"
        " command line `python -m jaxcal.prognose` writes the same folder).",
        "",
        "The UKF calibrates the `cmapss` engine's HPC and fan efficiency and flow "
        f"(`theta={','.join(PROGNOSIS_THETA)}`, the command line's default) on every "
        "row of the training and test units; the fleet's trend prior and failure "
        "boundary come from the training units' ends; each test unit's RUL is the "
        "median first crossing of the boundary by its posterior trend, with a 90 % "
        "interval (docs/prognosis.md).",
        "",
        "| | FD001 | FD002 |",
        "|---|---|---|",
    ]
    fds = [fd for fd in ("FD001", "FD002") if fd in rows]

    def row(label: str, key: str, fmt: str) -> str:
        cells = [
            fmt.format(rows[fd][key]) if fd in rows else "–"
            for fd in ("FD001", "FD002")
        ]
        return f"| {label} | " + " | ".join(cells) + " |"

    lines += [
        row("RMSE (cycles)", "rmse", "{:.2f}"),
        row("PHM08 score", "phm08_score", "{:.0f}"),
        row("90 % interval coverage", "coverage", "{:.2f}"),
        row("mean interval width (cycles)", "mean_width", "{:.0f}"),
        row("mean error (cycles, + late)", "mean_error", "{:+.2f}"),
        row("RMSE, prediction capped at 125", "rmse_capped_125", "{:.2f}"),
        row(
            "RMSE, prediction and truth capped at 125 (the piecewise-linear target; "
            "not the goal's scoring)",
            "rmse_both_capped_125",
            "{:.2f}",
        ),
        row("wall time, calibration included (s)", "seconds", "{:.0f}"),
    ]  # fmt: skip
    for label, fd1, fd2 in PUBLISHED:
        lines.append(f"| {label}: RMSE | {fd1:.2f} | {fd2:.2f} |")
    lines += [""]
    for fd in fds:
        lines.append(
            f"- **{fd}**: [report]({fd}/report.md); end of life driven by "
            + ", ".join(f"{n} ({k} units)" for n, k in rows[fd]["drivers"].items())
            + "."
        )
    lines += [
        "",
        "What limits the accuracy, lever by lever (trend family, noise scale, noise "
        "model, a denoised health index): [levers/](levers/README.md) "
        "(`python experiments/prognosis_levers.py`; measured with the HPC pair, "
        "`theta=HPC_eff_mod,HPC_flow_mod`, the default before the fan pair joined "
        "it). The same prognosis on a model of our own, from unlabelled CSVs: "
        "[heat_exchanger/](heat_exchanger/README.md) "
        "(`python experiments/prognosis_any_model.py`). On a fleet of two fault "
        "modes (HPC or fan, the shape of FD003/FD004, written by the engine): "
        "[two_modes/](two_modes/README.md) "
        "(`python experiments/prognosis_two_modes.py`), and with FD002's six "
        "operating conditions (FD004's shape): "
        "[two_modes_six_conditions/](two_modes_six_conditions/README.md) "
        "(`... conditions=FD002`).",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    try:
        cfg = parse_overrides(argv, PrognosisCmapssConfig())
        missing = [
            p
            for fd in cfg.files
            for p in _paths(cfg.data_dir, fd)
            if not os.path.isfile(p)
        ]
        if missing:
            raise FileNotFoundError(
                f"C-MAPSS file(s) not found: {', '.join(missing)} (set data_dir=)"
            )
    except (ValueError, FileNotFoundError) as err:
        print(f"prognosis_cmapss: {err}", file=sys.stderr)
        return 2
    enable_x64()
    enable_compilation_cache()
    rows = {}
    for fd in cfg.files:
        rows[fd] = _run(cfg, fd)
        print(
            f"{fd}: " + ", ".join(f"{k} {v}" for k, v in rows[fd].items()), flush=True
        )
    from jaxcal.diagnosis.report.write import write_text

    write_text(os.path.join(cfg.out, "README.md"), _readme(cfg, rows, argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
