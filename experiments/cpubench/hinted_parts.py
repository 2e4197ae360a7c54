"""Where the turbofan's warm-started single-sample solve spends its time (JSON).

Issue 41 item 2 asks ``StreamingCalibrator.step`` on the turbofan for at most 200 us a
row; the step is the engine's warm-started solve
(:func:`jaxcal.models.turbofan.physics.warm_start. evaluate_hinted`) plus a small
network. This prints, from one process with JAX's calls on the calling thread and the
variants' calls interleaved row by row along one smooth flight (so that a shared
machine's load falls on all alike):

* ``solve_us``: the deployed solve (Broyden from the hint, the cold solve as a
  ``lax.cond`` fall-back, the checks), median and 10th percentile;
* ``broyden_only_us``: Broyden's ``while_loop`` alone (no fall-back, no checks);
* ``unrolled_<k>_us``: exactly ``k`` Broyden updates written out (no ``while_loop``);
* ``residual_us``: one balance residual with the outputs (the unrolled one Broyden
  evaluates), and ``residual_kernels``: the kernels (fusions) XLA:CPU runs for it;
* ``updates_at_tol``: the mean Broyden updates a sample and the outputs' largest
  relative difference to the cold solve at each solver tolerance.

Usage::

    python experiments/cpubench/hinted_parts.py [rows=300] [out=FILE]
"""

from __future__ import annotations

import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.programs.packed import dispatch_is_synchronous
from jaxcal.deploy import synchronous_dispatch
from jaxcal.models.turbofan.physics import cycle, solver, warm_start
from jaxcal.models.turbofan.physics.design import design_point
from jaxcal.models.turbofan.physics.engine import load_engine


def _flight(rows: int):
    """``(w [T, 4], theta [T, 10])``: a climb with a slowly moving throttle, Mach and
    a health that drifts (consecutive samples are nearby problems)."""
    t = np.linspace(0.0, 1.0, rows)
    w = np.stack([20000 + 10000 * t, 0.5 + 0.2 * np.sin(6 * t),
                  80 + 5 * np.sin(9 * t), 500 + 10 * t], -1)  # fmt: skip
    return w, np.zeros((rows, 10)) + 1e-3 * t[:, None]


def _variants(engine, dp):
    """``name -> jitted (w, theta, hint) -> (x, hint)``."""

    def parts(w, theta):
        effects = jnp.zeros((cycle.NUM_EFFECTS,), w.dtype)
        p = jnp.concatenate([w, theta])
        residual = warm_start._residual_with_outputs(
            engine.design, dp, w, theta, effects
        )
        return p, residual

    def solve(w, theta, hint):
        x, _, hint = engine.evaluate_hinted(w, theta, hint)
        return x, hint

    def broyden_only(w, theta, hint):
        p, residual = parts(w, theta)
        start = hint._replace(z=solver.predicted_start(hint, p))
        z, _, _, jinv, (x, _) = solver.quasi_newton(residual, start, None, 1e-11, 10)
        sens = solver.secant_sensitivity(hint, p, z)
        return x, solver.Hint(z, jinv, hint.ok, p, sens)

    def unrolled(k):
        def run(w, theta, hint):
            p, residual = parts(w, theta)
            z, jinv = solver.predicted_start(hint, p), hint.jinv
            r, (x, _) = residual(z, None)
            for _ in range(k):
                s = -jinv @ r
                z = z + s
                r_new, (x, _) = residual(z, None)
                hy = jinv @ (r_new - r)
                jinv = jinv + jnp.outer(s - hy, s @ jinv) / (s @ hy)
                r = r_new
            sens = solver.secant_sensitivity(hint, p, z)
            return x, solver.Hint(z, jinv, hint.ok, p, sens)

        return run

    fns = {"solve": solve, "broyden_only": broyden_only}
    fns.update({f"unrolled_{k}": unrolled(k) for k in (2, 3)})
    return {name: jax.jit(fn) for name, fn in fns.items()}


def _kernels(compiled_text: str) -> int:
    return compiled_text.count("fusion(")


def main(argv: list[str]) -> int:
    opts = dict(a.split("=", 1) for a in argv)
    rows = int(opts.get("rows", 300))
    synchronous_dispatch()  # as a deployed stream runs (jaxcal.deploy)
    jax.config.update("jax_enable_x64", True)
    engine = load_engine("cmapss")
    dp = design_point(engine.design)
    w, theta = _flight(rows)
    fns = _variants(engine, dp)
    first = jax.jit(engine.evaluate_hinted)(w[0], theta[0], engine.initial_hint())[2]
    hints = dict.fromkeys(fns, first)
    times = {name: [] for name in fns}
    for fn in fns.values():
        jax.block_until_ready(fn(w[1], theta[1], first))  # compiled
    for t in range(1, rows):
        for name, fn in fns.items():
            tic = time.perf_counter()
            x, hints[name] = fn(w[t], theta[t], hints[name])
            np.asarray(x)
            times[name].append(time.perf_counter() - tic)
    out = {"rows": rows, "synchronous": dispatch_is_synchronous()}
    for name, ts in times.items():
        out[f"{name}_us"] = {"median": 1e6 * float(np.median(ts)),
                             "p10": 1e6 * float(np.percentile(ts, 10))}  # fmt: skip
    out["solve_kernels"] = _kernels(
        fns["solve"].lower(w[0], theta[0], first).compile().as_text()
    )

    def residual(z, w1, th1):  # the sample's inputs as arguments: nothing folded
        effects = jnp.zeros((cycle.NUM_EFFECTS,), w1.dtype)
        return warm_start._residual_with_outputs(engine.design, dp, w1, th1, effects)(
            z, None
        )

    one = jax.jit(residual)
    z, w0, th0 = np.asarray(first.z), w[0], theta[0]
    jax.block_until_ready(one(z, w0, th0))
    ts = []
    for _ in range(500):
        tic = time.perf_counter()
        jax.block_until_ready(one(z, w0, th0))
        ts.append(time.perf_counter() - tic)
    out["residual_us"] = {"median": 1e6 * float(np.median(ts)),
                          "p10": 1e6 * float(np.percentile(ts, 10))}  # fmt: skip
    out["residual_kernels"] = _kernels(one.lower(z, w0, th0).compile().as_text())
    cold = np.asarray(jax.jit(engine.evaluate)(w, theta)[0])
    out["updates_at_tol"] = {}
    for tol in (1e-11, 1e-9, 1e-8, 1e-6):
        cfg = solver.SolverConfig(tol=tol)

        def at(w1, th1, hint, cfg=cfg):
            return warm_start.evaluate_hinted(
                engine.design, w1, th1, hint, guess=engine.guess, solver_cfg=cfg,
                envelope=engine.envelope, dp=dp,
            )  # fmt: skip

        step, hint, iters, err = jax.jit(at), engine.initial_hint(), [], 0.0
        for t in range(rows):
            x, info, hint = step(w[t], theta[t], hint)
            iters.append(int(info.iterations))
            err = max(err, float(np.max(np.abs(np.asarray(x) / cold[t] - 1.0))))
        out["updates_at_tol"][f"{tol:g}"] = {
            "mean_updates": float(np.mean(iters[1:])), "max_rel_diff_vs_cold": err
        }  # fmt: skip
    text = json.dumps(out, indent=1)
    print(text)
    if "out" in opts:
        with open(opts["out"], "w") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
