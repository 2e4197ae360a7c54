"""Prognosis on a model of the project's own (issue 45, "any model"): heat exchangers
taken out for cleaning when their fouling reaches a declared limit.

    python experiments/prognosis_any_model.py [train_units=30] [test_units=30]
        [limit=0.45] [seed=0] [samples=1000] [data=data/prognosis/heat_exchanger]
        [out=results/prognosis/heat_exchanger]

The generator (:func:`make_fleet`) runs each unit of ``jaxcal.models.heat_exchanger`` at
random operating conditions inside its ``CONDITION_RANGE``. Deposits build up:
``fouling`` rises from a small initial value along ``exp(t / tau)`` (``tau`` log-uniform
from a third of the nominal life, clearly accelerating, to three lives, nearly linear)
with a small AR(1) wobble, and the unit is taken out at the first cycle its fouling
reaches ``limit``; ``dp_coeff`` grows linearly at a unit's own clogging pace (so its end
values scatter and do not mark the end of life); ``heat_loss`` stays nominal. Outputs
carry Gaussian noise. Test units are cut at random ages (10-90 % of their life), their
true RUL kept in ``RUL.txt``. The CSVs have no parameter columns: the twin only sees
conditions and outputs, as a user's data would be.

``jaxcal.prognose`` then runs twice: with ``boundary={"fouling": limit}`` declared,
and with the boundary learned from the training units' ends. Prints and writes
``<out>/summary.json`` (fleet plausibility, RMSE, coverage, PHM08 score, seconds per
stage), a ``README.md`` and each run's report
(``jaxcal.prognosis.report.write_prognosis``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
import warnings

import jax
import numpy as np
import pandas as pd

from jaxcal.cache import enable_compilation_cache
from jaxcal.diagnosis.report.write import write_text
from jaxcal.models import load
from jaxcal.precision import enable_x64
from jaxcal.prognosis import PrognosisConfig, prognose, read_truth, score
from jaxcal.prognosis.report import write_prognosis
from jaxcal.settings import parse_overrides

NOISE = {"T_hot_out": 0.1, "T_cold_out": 0.1, "dp_hot": 0.2, "duty": 1.0}
THETA = ("fouling", "dp_coeff")
CUT = (0.1, 0.9)  # test units are seen at this share of their life


@dataclasses.dataclass(frozen=True)
class AnyModelPrognosisConfig:
    train_units: int = 30  # run-to-failure units (their last row: the limit reached)
    test_units: int = 30  # units in service, cut at random ages
    life: tuple[int, int] = (120, 260)  # nominal lives (cycles) drawn uniformly
    limit: float = 0.45  # fouling at which a unit is taken out for cleaning
    seed: int = 0
    samples: int = 1000  # RUL samples per test unit
    data: str = "data/prognosis/heat_exchanger"  # the generated CSVs and RUL.txt
    out: str = "results/prognosis/heat_exchanger"


def _unit(rng, model, limit: float, life_range):
    """One unit's ``(theta [L, 3], w [L, 4])`` to the cycle ``L`` its fouling reaches
    ``limit`` (module docstring)."""
    nominal = int(rng.integers(*life_range))
    tau = nominal * np.exp(rng.uniform(-np.log(3.0), np.log(3.0)))  # log-uniform
    f0 = rng.uniform(0.0, 0.04)
    t = np.arange(1.0, 2 * nominal + 1.0)  # room past the nominal life for the wobble
    wobble = np.zeros(t.size)
    for k in range(1, t.size):  # deposits flake off and regrow: correlated, small
        wobble[k] = 0.8 * wobble[k - 1] + rng.normal(0.0, 0.002)
    fouling = f0 + (limit - f0) * np.expm1(t / tau) / np.expm1(nominal / tau) + wobble
    life = int(np.argmax(fouling >= limit)) + 1  # the first cycle at the limit
    fouling = np.minimum(fouling[:life], limit)
    dp_coeff = 10.0 + rng.uniform(0.01, 0.06) * t[:life]
    theta = np.stack([fouling, dp_coeff, np.full(life, 0.02)], axis=1)
    low, high = (np.asarray(b) for b in model.condition_range)
    return theta, rng.uniform(low, high, (life, low.size))


def _plausibility(thetas, num_train: int, truth) -> dict:
    """The fleet's shape in numbers: lives, where training units end, how much the
    fouling accelerates (its rise over the second half of a life against the first
    half's: 1 is linear)."""
    lives = np.array([th.shape[0] for th in thetas])
    ends = np.array([th[-1] for th in thetas[:num_train]])
    bend = np.array(
        [
            (th[-1, 0] - th[n // 2, 0]) / max(th[n // 2, 0] - th[0, 0], 1e-9)
            for th, n in zip(thetas, lives, strict=True)
        ]
    )

    def stats(v):
        return {"mean": float(np.mean(v)), "std": float(np.std(v))}

    return {
        "lives": {
            "min": int(lives.min()),
            "median": float(np.median(lives)),
            "max": int(lives.max()),
        },  # fmt: skip
        "train_fouling_end": stats(ends[:, 0]),
        "train_dp_coeff_end": stats(ends[:, 1]),
        "fouling_second_over_first_half_rise": {
            "median": float(np.median(bend)),
            "share_accelerating_gt_1.5": float(np.mean(bend > 1.5)),
            "share_nearly_linear_lt_1.2": float(np.mean(bend < 1.2)),
        },
        "truth_rul": stats(truth),
    }


def make_fleet(model, cfg: AnyModelPrognosisConfig):
    """``(train, test, truth, plausibility)``: unlabelled frames, the test units' true
    RULs ``[U]`` in unit order and the fleet's shape (:func:`_plausibility`)."""
    rng = np.random.default_rng(cfg.seed)
    num = cfg.train_units + cfg.test_units
    units = [_unit(rng, model, cfg.limit, cfg.life) for _ in range(num)]
    thetas = [th for th, _ in units]
    # every row at once: one compiled evaluation, not one per unit length
    evaluate = jax.jit(jax.vmap(lambda w_t, th: model.evaluate(w_t, th)[0]))
    x = np.asarray(
        evaluate(np.concatenate([w for _, w in units]), np.concatenate(thetas))
    )
    x = x + rng.standard_normal(x.shape) * np.array([NOISE[s] for s in NOISE])
    frames, truth, first = [], [], 0
    for u, (theta, w) in enumerate(units):
        life = theta.shape[0]
        frame = pd.DataFrame({"unit": u + 1, "time": np.arange(1.0, life + 1.0)})
        frame[list(model.condition_names)] = w
        frame[list(NOISE)] = x[first : first + life]
        first += life
        if u >= cfg.train_units:  # in service: seen up to a random age
            rows = int(rng.integers(int(CUT[0] * life), int(CUT[1] * life)))
            truth.append(life - rows)  # time = row number: the rest of the life
            frame = frame.iloc[:rows]
        frames.append(frame)
    truth = np.array(truth, np.float64)
    train = pd.concat(frames[: cfg.train_units], ignore_index=True)
    test = pd.concat(frames[cfg.train_units :], ignore_index=True)
    return train, test, truth, _plausibility(thetas, cfg.train_units, truth)


def _readme(summary: dict, argv: list[str]) -> str:
    """The results page: the fleet, and the two runs side by side."""
    fleet = summary["fleet"]
    rows = [
        "# Prognosis on a model of our own: heat exchangers fouling toward a limit",
        "",
        "Command: `python experiments/prognosis_any_model.py"
        + "".join(f" {a}" for a in argv)
        + "`. The generator writes unlabelled CSVs (unit, time, the four conditions "
        "and four outputs of `jaxcal.models.heat_exchanger`; no parameter column) and "
        "the test units' true RULs; `jaxcal.prognosis.prognose` calibrates "
        "`fouling` and `dp_coeff` with the UKF and predicts (docs/prognosis.md).",
        "",
        f"The fleet: `{json.dumps(fleet)}`.",
        "",
        "| boundary | RMSE | mean error | PHM08 | 90 % coverage | CRPS | median width "
        "| trend / noise scale | wall s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for run in ("declared", "learned"):
        r = summary[run]
        s = r["score"]
        rows.append(
            f"| {run} ([report]({'' if run == 'declared' else 'learned/'}report.md))"
            f" | {s['rmse']:.1f} | {s['mean_error']:+.1f} | {s['phm08_score']:.0f} | "
            f"{s['coverage']:.2f} | {s['crps']:.1f} | {s['median_width']:.0f} | "
            f"{r['chosen']['trend']} / {r['chosen']['noise_scale']:g} | "
            f"{r['seconds']['total']:.0f} |"
        )
    return "\n".join(rows) + "\n"


def _run(model, paths, truth, cfg, boundary, out: str) -> dict:
    """One ``prognose`` run, scored, with its report in ``out``."""
    start = time.perf_counter()
    result = prognose(
        model, paths["train"], paths["test"], theta=THETA, boundary=boundary,
        config=PrognosisConfig(samples=cfg.samples, seed=cfg.seed), progress=False,
    )  # fmt: skip
    wall = time.perf_counter() - start
    pred = result.prediction
    # the upper end is the search horizon for a unit whose samples often cross no
    # boundary: the median width is the typical one, the mean is skewed by those
    width = pred.rul_high - pred.rul_low
    train = result.train
    last = train.theta[np.arange(train.unit.size), train.mask.sum(1) - 1]
    drivers = {n: int(sum(d == n for d in pred.driver)) for n in THETA}
    start = time.perf_counter()
    write_prognosis(
        out, result, truth=truth, source=paths, config=cfg, progress=False,
        unit_figures=pred.unit[::3],  # a third of the units: the pages stay small
    )  # fmt: skip
    report_seconds = time.perf_counter() - start
    return {
        "boundary": "declared" if boundary else "learned",
        "score": {
            **score(pred.rul, pred.rul_low, pred.rul_high, truth, pred.samples),
            "median_width": float(np.median(width)),
            "units_high_at_horizon": int(np.sum(pred.censored >= 0.05)),
        },
        "seconds": {**result.timings, "total": wall, "report": report_seconds},
        "chosen": {k: result.noise_check[k] for k in ("trend", "noise_scale")},
        "held_out_check": result.noise_check,
        "degradation": result.model.to_json(),
        "calibrated_end": {
            n: {"mean": float(last[:, i].mean()), "std": float(last[:, i].std())}
            for i, n in enumerate(THETA)
        },
        "drivers": drivers,
        "censored_units": int((pred.censored > 0.5).sum()),
        "units": [
            {
                "unit": int(u),
                "now": float(n),
                "truth": float(t),
                "rul": float(r),
                "low": float(lo),
                "high": float(hi),
                "censored": float(c),
            }
            for u, n, t, r, lo, hi, c in zip(
                pred.unit,
                pred.now,
                truth,
                pred.rul,
                pred.rul_low,
                pred.rul_high,
                pred.censored,
                strict=True,
            )
        ],  # fmt: skip
        "notes": list(result.notes),
        "report": out,
    }


def main(argv: list[str]) -> int:
    try:
        cfg = parse_overrides(argv, AnyModelPrognosisConfig())
    except ValueError as err:
        print(f"prognosis_any_model: {err}", file=sys.stderr)
        return 2
    enable_x64()
    enable_compilation_cache()
    # the calibrator's warnings (drift faster than its random walk, rows at a bound)
    # are kept in each result's notes, written to summary.json: not repeated here
    warnings.filterwarnings("ignore", "jaxcal.calibrate", UserWarning)
    model = load("heat_exchanger")
    start = time.perf_counter()
    train, test, truth, plausible = make_fleet(model, cfg)
    generate = time.perf_counter() - start
    os.makedirs(cfg.data, exist_ok=True)
    paths = {k: os.path.join(cfg.data, f"{k}.csv") for k in ("train", "test")}
    train.to_csv(paths["train"], index=False)
    test.to_csv(paths["test"], index=False)
    truth_path = os.path.join(cfg.data, "RUL.txt")
    np.savetxt(truth_path, truth, fmt="%d")
    truth = read_truth(truth_path, cfg.test_units)  # as a user's truth file is read
    summary = {
        "model": "heat_exchanger",
        "config": dataclasses.asdict(cfg),
        "data": {**paths, "truth": truth_path, "rows": [len(train), len(test)]},
        "fleet": plausible,
        "generate_seconds": generate,
        "declared": _run(model, paths, truth, cfg, {"fouling": cfg.limit}, cfg.out),
        "learned": _run(
            model, paths, truth, cfg, None, os.path.join(cfg.out, "learned")
        ),
    }
    write_text(os.path.join(cfg.out, "summary.json"), json.dumps(summary, indent=2))
    write_text(os.path.join(cfg.out, "README.md"), _readme(summary, argv))
    brief = {
        run: {
            **summary[run]["score"],
            "chosen": summary[run]["chosen"],
            "seconds": summary[run]["seconds"],
        }
        for run in ("declared", "learned")
    }
    print(json.dumps({"fleet": plausible, **brief}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
