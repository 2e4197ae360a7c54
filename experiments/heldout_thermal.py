"""Held-out check of the default preset on a model nothing was tuned on (issue 41).

    python experiments/heldout_thermal.py [seed] [out]

A heated room with memory (``experiments/thermal_room.py``: two states, three
parameters, three outputs), 12 units x 300 rows drifting, written after the output-bias
states were chosen. Trains the untrained start, the actor tuned alone
(``tune.bias=false``) and the default preset from the file without parameter
columns, and scores each and the UKF on the test units 10-12 clean and under each
effect of ``experiments/policy_robust.py``. Writes ``<out>/results.json``
(default ``results/policy_robust/bias/heldout_thermal``; runs and data under
``runs/heldout_thermal``).
"""

import json
import os
import shutil
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from policy_robust import EFFECTS, _score, with_effect  # noqa: E402
from thermal_room import thermal_init, thermal_model, thermal_step  # noqa: E402
from unseen_models import _schedule  # noqa: E402

NOISE = {"T_r": 0.1, "T_w": 0.1, "flux": 0.05}


def main(argv: list[str]) -> int:
    import jaxcal

    jax.config.update("jax_enable_x64", True)  # entry point: the UKF wants float64
    model = thermal_model()
    rng = np.random.default_rng(int(argv[0]) if argv else 0)
    names = list(model.parameter_names)
    low, high = model.condition_range
    frames = []
    for unit in range(1, 13):
        rows = 300
        t = np.arange(rows)
        start = rng.uniform([0.85, 700.0, 250.0], [1.0, 900.0, 330.0])
        rise = np.array([-0.2, -250.0, 100.0]) * rng.uniform(0.4, 1.0, 3)
        theta = start + rise * (t[:, None] / rows) ** 1.2
        w = _schedule(rng, rows, low, high)

        def body(z, inp):
            return thermal_step(z, *inp)

        x = np.asarray(
            jax.lax.scan(
                body,
                thermal_init(jnp.asarray(w[0]), jnp.asarray(theta[0])),
                (jnp.asarray(w), jnp.asarray(theta)),
            )[1]
        )
        x = x + np.array([NOISE[o] for o in model.output_names]) * rng.normal(
            size=x.shape
        )
        f = pd.DataFrame(w, columns=list(model.condition_names))
        f[list(model.output_names)] = x
        f["unit"], f["time"] = unit, t
        f[names] = theta
        frames.append(f)
    fleet = pd.concat(frames, ignore_index=True)
    out = argv[1] if len(argv) > 1 else "results/policy_robust/bias/heldout_thermal"
    work = "runs/heldout_thermal"
    os.makedirs(out, exist_ok=True)
    os.makedirs(work, exist_ok=True)
    fleet.drop(columns=names).to_csv(f"{work}/fleet.csv", index=False)
    test = fleet[fleet.unit.isin([10, 11, 12])].reset_index(drop=True)
    spec = f"{os.path.join(HERE, 'thermal_room.py')}:thermal_model"
    half = 0.5 * (np.asarray(model.bounds[1]) - np.asarray(model.bounds[0]))
    outputs = list(model.output_names)
    tests = {
        lab: with_effect(test, outputs, NOISE, k, s, np.random.default_rng(7))
        for lab, (k, s) in EFFECTS.items()
    }

    def scores(method: str, **options) -> dict:
        """Theta RMSE of ``method`` on each test frame (half-widths of the box)."""
        out = {}
        for lab, fr in tests.items():
            r = jaxcal.calibrate(spec, fr, method=method, theta=names, progress=False,
                                 misfit="keep", **options)  # fmt: skip
            out[lab] = _score(r, fr, names, half)
        return out

    res = {"ukf": scores("ukf", noise=NOISE)}
    print("ukf", res["ukf"], flush=True)
    noise_arg = ",".join(f"{k}:{v}" for k, v in NOISE.items())
    for variant, extra in (
        ("start", ["budget.num_chunks=0", "tune.steps=0"]),
        ("actor-tuned", ["tune.bias=false"]),
        ("default", []),
    ):
        shutil.rmtree(f"{work}/thermal-{variant}", ignore_errors=True)  # afresh
        cmd = [
            sys.executable,
            "-m",
            "jaxcal.train",
            f"model={spec}",
            f"data={work}/fleet.csv",
            f"theta={','.join(names)}",
            "test_units=10,11,12",
            f"noise={noise_arg}",
            f"name=thermal-{variant}",
            f"output.runs_dir={work}",
            "output.progress=false",
            *extra,
        ]
        tic = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode:
            print(p.stderr[-3000:])
            return 1
        job = time.perf_counter() - tic
        line = [l for l in p.stdout.splitlines() if "training " in l and "start" in l]
        sc = scores("policy", run=f"{work}/thermal-{variant}")
        res[variant] = {"job_s": job, "theta_rmse": sc, "line": line}
        print(
            variant,
            round(job),
            {k: round(v / res["ukf"][k], 3) for k, v in sc.items()},
            line,
            flush=True,
        )
    json.dump(res, open(f"{out}/results.json", "w"), indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
