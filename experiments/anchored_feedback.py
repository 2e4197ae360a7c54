"""A feedback bounded around the absolute policy: precision and robustness at once?

The feedback policy (CLAC-inc, incremental actions through F) is 1.4x the UKF on clean
Dataset #1 but chases a biased model (F x 1.02) like the UKF; the absolute policy
(CLAC through D) is 30x less precise but robust (0.08x the UKF under that bias). This
measures the obvious composition, deployed from the two trained runs as they are:

    theta_t = clip(theta_feedback_t, theta_absolute_t - b, theta_absolute_t + b)

with the feedback's carried theta replaced by the clipped one (so it cannot run
away), and b the q-quantile of the absolute policy's |error| on the validation unit
(labels of a held-out dev unit; never test labels). Both policies see the same
perturbation of their own model (D for the absolute one, F for the feedback), as in
the paper's robustness study. Writes ``results/train/anchored.json``.

Usage::

    python experiments/anchored_feedback.py absolute=runs/<absolute run> \
        feedback=runs/cmapss-clac-physics-inc-s0 [data=data/cmapss.h5]
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # the feedback runs on the engine's F

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxcal.calibrators.interface import Calibrator, CalStepOutput  # noqa: E402
from jaxcal.paper.compare import evaluate_method  # noqa: E402
from jaxcal.paper.methods import make_method  # noqa: E402
from jaxcal.paper.suite import Suite, SuiteConfig  # noqa: E402
from jaxcal.runs.folder import write_json  # noqa: E402

QUANTILES = (0.9, 0.99, 1.0)  # b = this quantile of the absolute policy's val error
VARIANTS = {"clean": (1.0, 0.0), "bias": (1.02, 0.0)}


def anchored(feedback: Calibrator, anchor: Calibrator, halfwidth) -> Calibrator:
    """The feedback's theta clipped to anchor +- halfwidth (carried clipped)."""

    def init(key, w0, x0):
        return feedback.init(key, w0, x0), anchor.init(key, w0, x0)

    def step(state, w, x):
        fb_state, an_state = state
        an_state, an_out = anchor.step(an_state, w, x)
        fb_state, fb_out = feedback.step(fb_state, w, x)
        low = an_out.theta.astype(fb_out.theta.dtype) - halfwidth
        theta = jnp.clip(fb_out.theta, low, low + 2.0 * halfwidth)
        # the paper's policy methods carry a PRNG key beside the policy state
        policy_state = fb_state.inner.replace(
            theta=theta.astype(fb_state.inner.theta.dtype)
        )
        fb_state = fb_state.replace(inner=policy_state)
        return (fb_state, an_state), CalStepOutput(theta=theta, xhat=fb_out.xhat)

    return Calibrator(init, step)


def main(argv: list[str]) -> int:
    args = dict(a.split("=", 1) for a in argv)
    data = args.get("data", "data/cmapss.h5")
    runs = {"CLAC": args["absolute"], "CLAC-inc": args["feedback"]}
    suite = Suite(data, runs, SuiteConfig(), Path("/tmp/anchored-models"))
    absolute, feedback = suite.method("CLAC"), suite.method("CLAC-inc")
    val = suite.data.val
    with jax.enable_x64(False):  # the absolute policy as it is scored (float32)
        val_run = evaluate_method(absolute, val, suite.problem)
    err = np.abs(val_run.theta - val.theta)[val.mask]  # [N, P]
    out = {
        "absolute_run": runs["CLAC"],
        "feedback_run": runs["CLAC-inc"],
        "val_units": val.unit_ids.tolist(),
        "absolute_val_theta_rmse": val_run.scores["theta_rmse"],
        "rows": [],
    }
    units = suite.test_units()
    for q in QUANTILES:
        b = jnp.asarray(np.quantile(err, q, axis=0))

        def build(bias, sigma, b=b):
            return anchored(feedback.build(bias, sigma), absolute.build(bias, sigma), b)

        method = make_method(
            f"anchored-q{q}", build, np.float64, {}, check=feedback.check
        )
        row = {"quantile": q, "halfwidth": np.asarray(b).tolist()}
        for variant, (bias, sigma) in VARIANTS.items():
            tic = time.perf_counter()
            run = evaluate_method(
                method, units, suite.problem, bias=bias, noise_sigma=sigma
            )
            row[variant] = run.scores["theta_rmse"]
            row[f"{variant}_seconds"] = time.perf_counter() - tic
            print(
                f"q={q} b={np.asarray(b)} {variant}: theta RMSE {row[variant]:.3e}",
                flush=True,
            )
        out["rows"].append(row)
    write_json(Path("results/train/anchored.json"), out)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
