"""What training adds to the policy's untrained start, clean and under model error
(issue 41): each lever measured on its own against the untrained start and the UKF.

    python experiments/policy_robust.py [cases=heat_exchanger,pump,motor]
        [variants=start,default,theta,effects,both] [out=results/policy_robust]
        [data=data/policy_robust] [runs=runs/policy_robust] [seed=0]
        [output=<the effects' output>] [reuse=false]

Per case (a fleet of ``experiments/policy_any_model.py``: 12 units, test units
10-12, trained from the file without parameter columns, ``noise=`` given), each
variant is one ``python -m jaxcal.train`` with the default preset and:

* ``start``: ``budget.num_chunks=0``: the untrained policy (the extended Kalman
  filter's step the actor starts as), kept as chunk 0;
* ``default``: the default preset as it is;
* ``theta``: ``env.theta_cost=<theta_cost>``: the cost adds the theta error where the
  truth is known (the simulated training units);
* ``effects``: ``simulate.effects=<effects>``: that share of the simulated training
  units carries an undeclared effect (a bias, step, drift, gain or AR(1) noise);
* ``both``: the two together;
* ``adapt_start``, ``adapt``, ``adapt_effects``: ``env.filter_adapt=<adapt>`` (the
  filter weighs each output by the noise its innovations show beyond what theta
  explains), untrained, with the default training, and with ``effects``;
* ``tune``, ``tune_effects``, ``rl_tune_effects``: ``tune.steps=<tune>`` (the kept
  actor tuned by gradient through the deployed filter on simulated units' theta
  error, :mod:`jaxcal.training.stages.tune`) from the untrained start, the same with
  ``effects``, and after the default training with ``effects``;
* ``balanced``: the default with ``tune.effects=<effects>`` (a share of the tuning
  units with effects, the score half clean, half effects, clean not above the
  start's).

Every kept policy and the UKF (``jaxcal.calibrate``, the same noise) then run on the
test units clean and with one effect in every test unit (:data:`EFFECTS`, in units
of the noisiest-relative output's noise std), scored by theta RMSE against the labels
in box half-widths (one number per model: the mean over parameters). Writes
``<out>/results.json`` and ``<out>/README.md``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pandas as pd

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from policy_any_model import TEST_UNITS, _case, split_files  # noqa: E402

# (kind, size in noise stds): the test units' effects, on one output from a third of
# each unit (ar1: every output, the whole unit)
EFFECTS = {
    "clean": ("none", 0.0),
    "bias 3σ": ("bias", 3.0),
    "drift 4σ": ("drift", 4.0),
    "gain 3σ": ("gain", 3.0),
    "AR(1) 0.8": ("ar1", 0.8),
}
VARIANTS = {
    "start": ["budget.num_chunks=0", "tune.steps=0"],
    # the default before issue 41's tuning: six chunks, no effects, no tuning
    "rl": ["simulate.effects=0", "tune.steps=0", "budget.patience=null"],
    "default": [],
    "theta": ["env.theta_cost={theta_cost}"],
    "effects": ["simulate.effects={effects}"],
    "both": ["env.theta_cost={theta_cost}", "simulate.effects={effects}"],
    "adapt_start": ["env.filter_adapt={adapt}", "budget.num_chunks=0"],
    "adapt": ["env.filter_adapt={adapt}"],
    "adapt_effects": ["env.filter_adapt={adapt}", "simulate.effects={effects}"],
    "tune": ["budget.num_chunks=0", "tune.steps={tune}"],
    "tune_effects": [
        "budget.num_chunks=0",
        "simulate.effects={effects}",
        "tune.steps={tune}",
    ],
    "rl_tune_effects": ["simulate.effects={effects}", "tune.steps={tune}"],
    # the default with a share of the tuning units carrying effects, scored half
    # clean, half effects, clean never worse than the start (tune.effects)
    "balanced": ["tune.effects={effects}"],
    # the same, the clean selection units allowed item 1's 5 %, the units drawn
    # across the box not guarded (faster changes than the data's drifts)
    "robust": [
        "tune.effects={effects}",
        "tune.clean_limit=1.05",
        "tune.clean_tolerance=2.0",
        "tune.patience=6",
        "tune.steps=600",
    ],
    # the default with the filter's output-bias states tuned beside the actor
    # (tune.bias: the default since results/policy_robust/bias)
    "bias": ["tune.bias=true"],
    # the default before it: the actor tuned alone
    "actor-tuned": ["tune.bias=false"],
    # the default with the units drawn across the box within 2x (not 1.5x)
    "box-2x": ["tune.clean_tolerance=1.0"],
    # the default with the units drawn across the box within 1.5x (not 2x)
    "box15": ["tune.clean_tolerance=0.5"],
    # the same scored on the effects alone (the clean units a limit only)
    "robust_e": [
        "tune.effects={effects}",
        "tune.effects_weight=1.0",
        "tune.clean_limit=1.05",
        "tune.clean_tolerance=2.0",
        "tune.patience=6",
        "tune.steps=600",
    ],
}


def with_effect(frame, outputs, noise: dict, kind: str, size: float, rng):
    """The test frame with ``kind`` in every unit (on its first output whose noise is
    given, from a third of each unit's rows)."""
    frame = frame.copy()
    out = outputs[0]
    sd = float(noise[out])
    for _, rows in frame.groupby("unit").groups.items():
        n = len(rows)
        ramp = np.zeros(n)
        ramp[n // 3 :] = 1.0
        if kind == "bias":
            frame.loc[rows, out] += size * sd * ramp
        elif kind == "drift":
            ramp[n // 3 :] = np.linspace(0, 1, n - n // 3)
            frame.loc[rows, out] += size * sd * ramp
        elif kind == "gain":
            level = float(np.mean(np.abs(frame.loc[rows, out])))
            frame.loc[rows, out] += size * sd / level * frame.loc[rows, out] * ramp
        elif kind == "ar1":  # re-colour: add an AR(1) of the noise's std on top
            for o in outputs:
                e = rng.normal(size=n) * float(noise[o])
                ar = np.empty(n)
                ar[0] = e[0]
                for t in range(1, n):  # an experiment's data, host side
                    ar[t] = size * ar[t - 1] + np.sqrt(1 - size**2) * e[t]
                frame.loc[rows, o] += ar
    return frame


def _seconds(job) -> str:
    return "-" if job is None else f"{job:.0f}"  # "-": a reused run


def _score(res, test: pd.DataFrame, theta, half) -> float:
    err = (res.theta - test[theta].to_numpy()) / half
    ok = np.asarray(res.valid, bool)
    return float(np.mean(np.sqrt(np.mean(err[ok] ** 2, axis=0))))


def run_case(name: str, opts: dict) -> dict:
    import jaxcal

    spec, fleet, theta, noise = _case(name, int(opts["seed"]))
    model = jaxcal.models.load(spec)
    low, high = model.bounds
    index = [model.parameter_names.index(t) for t in theta]
    half = 0.5 * (high[index] - low[index])
    unlabelled, test = split_files(name, spec, fleet, opts["data"])
    outputs = [o for o in model.output_names if o in noise]
    if opts["output"]:  # the effect on this output (ar1: still every output)
        if opts["output"] not in outputs:
            raise ValueError(f"output={opts['output']}: not one of {outputs}")
        outputs.insert(0, outputs.pop(outputs.index(opts["output"])))
    tests = {
        label: with_effect(test, outputs, noise, kind, size, np.random.default_rng(7))
        for label, (kind, size) in EFFECTS.items()
    }
    result = {"model": spec, "theta": theta, "noise": noise, "ukf": {}, "runs": {}}
    for label, frame in tests.items():
        res = jaxcal.calibrate(
            spec, frame, method="ukf", theta=theta, noise=noise, progress=False,
            misfit="keep",
        )  # fmt: skip
        result["ukf"][label] = _score(res, frame, theta, half)
    noise_arg = ",".join(f"{k}:{v}" for k, v in noise.items())
    for variant in opts["variants"]:
        extra = [
            a.format(
                theta_cost=opts["theta_cost"],
                effects=opts["effects"],
                adapt=opts["adapt"],
                tune=opts["tune"],
            )  # fmt: skip
            for a in VARIANTS[variant]
        ]
        run_dir = os.path.join(opts["runs"], f"{name}-{variant}")
        reuse = opts["reuse"] and os.path.isfile(os.path.join(run_dir, "final.json"))
        if os.path.isdir(run_dir) and not reuse:
            shutil.rmtree(run_dir)
        cmd = [
            sys.executable, "-m", "jaxcal.train", f"model={spec}",
            f"data={unlabelled}", f"theta={','.join(theta)}",
            f"test_units={','.join(map(str, TEST_UNITS))}", f"noise={noise_arg}",
            f"name={name}-{variant}", f"output.runs_dir={opts['runs']}",
            "output.progress=false", *extra,
        ]  # fmt: skip
        tic = time.perf_counter()
        if not reuse:
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        job = None if reuse else time.perf_counter() - tic
        with open(os.path.join(run_dir, "final.json")) as f:
            final = json.load(f)
        scores = {}
        for label, frame in tests.items():
            res = jaxcal.calibrate(
                spec, frame, method="policy", theta=theta, run=run_dir,
                progress=False, misfit="keep",
            )  # fmt: skip
            scores[label] = _score(res, frame, theta, half)
        result["runs"][variant] = {
            "args": extra,
            "job_seconds": job,
            "selected_chunk": final["selected_chunk"],
            "training_gain": final.get("training_gain"),
            "theta_rmse": scores,
        }
        print(name, variant, json.dumps(result["runs"][variant]), flush=True)
    return result


def _page(results: dict, opts: dict) -> str:
    labels = list(EFFECTS)
    lines = [
        "# What training adds to the policy, clean and under model error",
        "",
        f"`python experiments/policy_robust.py cases={','.join(results)} "
        f"variants={','.join(opts['variants'])} theta_cost={opts['theta_cost']} "
        f"effects={opts['effects']} adapt={opts['adapt']} seed={opts['seed']}` "
        "(this machine, 2 cores). "
        "Theta RMSE in box half-widths (mean over parameters) on the test units "
        "(10-12), clean and with one effect in every test unit on the first output "
        "from a third of each unit; `policy / UKF` beside each. `start`: the "
        "untrained policy (the extended Kalman filter's step), the others trained "
        "by the default preset (see the script's docstring).",
        "",
    ]
    for name, res in results.items():
        lines += [
            f"## {name}",
            "",
            "| variant | job s | kept chunk | "
            + " | ".join(f"{lab} (x UKF)" for lab in labels)
            + " |",
            "|---|---|---|" + "---|" * len(labels),
            "| UKF | - | - | "
            + " | ".join(f"{res['ukf'][lab]:.4g}" for lab in labels)
            + " |",
        ]
        for variant, run in res["runs"].items():
            cells = [
                f"{run['theta_rmse'][lab]:.4g} "
                f"({run['theta_rmse'][lab] / res['ukf'][lab]:.2f})"
                for lab in labels
            ]
            lines.append(
                f"| {variant} | {_seconds(run['job_seconds'])} | "
                f"{run['selected_chunk']} | " + " | ".join(cells) + " |"
            )
        lines.append("")
    return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class Options:
    """The script's ``key=value`` options (module docstring)."""

    cases: str = "heat_exchanger,pump,motor"
    variants: str = "start,default,theta,effects,both"
    out: str = "results/policy_robust"
    data: str = "data/policy_robust"
    runs: str = "runs/policy_robust"
    seed: int = 0
    theta_cost: float = 30.0
    effects: float = 0.5
    adapt: int = 32
    tune: int = 300  # tune.steps of the tune variants
    output: str = ""  # the effects' output ("": the first whose noise is given)
    reuse: bool = False  # score a variant's existing run instead of training it


def main(argv: list[str]) -> int:
    from jaxcal.settings import parse_overrides

    try:
        opts = dataclasses.asdict(parse_overrides(argv, Options()))
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    opts["variants"] = opts["variants"].split(",")
    import jax

    jax.config.update("jax_enable_x64", True)  # entry point: the UKF wants float64
    results = {}
    kept = os.path.join(opts["out"], "results.json")
    if os.path.exists(kept):  # other cases of an earlier call are kept beside
        with open(kept) as f:
            results = json.load(f)["results"]
    for name in opts["cases"].split(","):
        new = run_case(name, opts)
        if name in results:  # the variants of an earlier call kept, these replaced
            new["runs"] = {**results[name]["runs"], **new["runs"]}
        results[name] = new
    os.makedirs(opts["out"], exist_ok=True)
    with open(os.path.join(opts["out"], "results.json"), "w") as f:
        json.dump({"options": opts, "results": results}, f, indent=1)
    with open(os.path.join(opts["out"], "README.md"), "w") as f:
        f.write(_page(results, opts) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
