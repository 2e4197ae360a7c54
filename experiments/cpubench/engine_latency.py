"""Single-stream latency of the engine F and of the two F-based deployments (JSON).

Issue 15 ("deploy speed-up over the UKF >= 5"): the paper measures seconds per sample
of one jitted calibrator ``step`` per sample (:func:`jaxcal.paper.compare.
measure_latency`). This prints, from ONE process so that the ratio is fair:

* ``F_single_cold_us``: one jitted ``model.evaluate(w, theta)`` (Newton from the
  guess table), median of ``repeats`` calls;
* ``F_single_warm_z0_us``: the same with the previous sample's solution as the
  Newton start (``Engine.evaluate(..., z0=)``), along consecutive samples of one unit;
* ``F_single_hinted_us``: the warm-started stream (``Engine.evaluate_hinted``, the
  previous sample's hint), its mean Broyden iterations and its largest relative
  difference to the cold F (when the engine has it);
* ``F_vmap3_us``: three thetas at once (the UKF's sigma points of a one-parameter
  problem);
* ``residual_us`` / ``residual_unrolled_us`` / ``jacobian_us`` /
  ``design_point_us``: F's parts (one balance residual as F's Newton loop evaluates
  it, the warm path's unrolled one, its forward-mode Jacobian, the design point F
  recomputes per call): where a cold F's time goes;
* ``UKF`` / ``CLAC`` / ``CLAC-inc`` / ``CLAC-gate``: :func:`measure_latency` on
  Dataset #1's first test unit in the deployed form (:meth:`Method.deploy`: clean
  model, no noise key; the policies on F warm-started), with
  ``deployed_vs_scored_max_abs_theta_diff`` against the scored form along that unit,
  ``ratio_ukf_over_<name>``, and the same timing of the form the scores run
  (``build(1, 0)``: a PRNG key for the model's noise in its state, and for a policy
  on F the cold solve: ``perturbable_form_median_s``,
  ``perturbable_form_ratio_ukf_over_<name>``).

Usage::

    python experiments/cpubench/engine_latency.py [data=data/cmapss.h5] \
        [feedback=runs/cmapss-clac-physics-inc-s0] \
        [absolute=runs/cmapss-clac-surrogate-s0-absolute] \
        [models=results/paper/models/ds1] [repeats=300] [out=FILE]

``models`` holds CLAC-gate's fit (``clac-gate.json``, the paper's
``fit-ds1-CLAC-gate`` step); without it the gate is skipped.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # the engine's Newton solve is float64

import numpy as np  # noqa: E402

from jaxcal.paper.compare import measure_latency  # noqa: E402
from jaxcal.paper.suite import Suite, SuiteConfig  # noqa: E402


def _median_us(fn, args_list, repeats: int) -> float:
    """Median wall time of ``fn(*args)`` over ``repeats`` calls (cycling args)."""
    jax.block_until_ready(fn(*args_list[0]))
    times = np.empty(repeats)
    for i in range(repeats):
        args = args_list[(i + 1) % len(args_list)]
        tic = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times[i] = time.perf_counter() - tic
    return float(np.median(times) * 1e6)


def engine_numbers(suite: Suite, units, repeats: int) -> dict:
    """F alone: cold, warm along the unit, vmap over three thetas."""
    engine = suite.engine
    length = int(units.lengths[0])
    w = np.asarray(units.w[0, :length], np.float64)
    theta_full = np.tile(np.asarray(suite.problem.theta_base, np.float64), (length, 1))
    index = [
        list(suite.problem.model.parameter_names).index(n)
        for n in suite.problem.theta_names
    ]
    theta_full[:, index] = units.theta[0, :length]
    cold = jax.jit(lambda w, th: engine.evaluate(w, th)[0])
    warm = jax.jit(lambda w, th, z: engine.evaluate(w, th, z0=z))
    _, info = jax.jit(engine.evaluate)(w, theta_full)  # the previous sample's z
    z_prev = np.roll(np.asarray(info.z), 1, axis=0)
    three = np.stack([theta_full[0]] * 3)
    three[:, index[0]] += np.array([-0.002, 0.0, 0.002])
    vmap3 = jax.jit(lambda w, th: jax.vmap(lambda t: engine.evaluate(w, t)[0])(th))
    rows = [(w[t], theta_full[t]) for t in range(length)]
    out = {
        "F_single_cold_us": _median_us(cold, rows, repeats),
        "F_single_warm_z0_us": _median_us(
            warm, [(w[t], theta_full[t], z_prev[t]) for t in range(1, length)], repeats
        ),
        "F_vmap3_us": _median_us(
            vmap3, [(w[t], three) for t in range(length)], repeats
        ),
        "cold_iterations_mean": float(np.mean(info.iterations)),
        "warm_z0_iterations_mean": float(
            np.mean(warm(w[1:], theta_full[1:], z_prev[1:])[1].iterations)
        ),
    }
    out.update(_parts_us(engine, w[0], theta_full[0], np.asarray(info.z[0]), repeats))
    if hasattr(engine, "evaluate_hinted"):  # the warm-started stream (new code)
        hinted = jax.jit(engine.evaluate_hinted)
        hint = engine.initial_hint()
        times, iters, err = [], [], 0.0
        x_cold = np.asarray(jax.jit(engine.evaluate)(w, theta_full)[0])
        for i in range(repeats + 1):
            t = i % length
            tic = time.perf_counter()
            x, info_t, hint = hinted(w[t], theta_full[t], hint)
            x = np.asarray(x)
            if i:  # the first call compiles
                times.append(time.perf_counter() - tic)
            iters.append(int(info_t.iterations))
            err = max(err, float(np.max(np.abs(x / x_cold[t] - 1.0))))
        out.update(
            F_single_hinted_us=float(np.median(times) * 1e6),
            hinted_iterations_mean=float(np.mean(iters[1:])),
            hinted_max_rel_diff_vs_cold=err,
        )
    return out


def _deployed_vs_scored(method, units, count: int = 400) -> float:
    """max |theta| difference between a method's deployed form and its scored
    form along the first ``count`` samples of the first test unit."""
    length = min(int(units.lengths[0]), count)
    w, x = units.w[0, :length], units.x[0, :length]
    thetas = []
    with jax.enable_x64(method.dtype == np.float64):
        for cal in (method.deploy(), _perturbable(method)):
            step = jax.jit(cal.step)
            state = cal.init(jax.random.key(0), w[0], x[0])
            rows = []
            for t in range(length):
                state, out = step(state, w[t], x[t])
                rows.append(np.asarray(out.theta))
            thetas.append(np.stack(rows))
    return float(np.max(np.abs(thetas[0] - thetas[1])))


def _perturbable(method):
    """The method as the paper's scores run it, unperturbed (its noise key kept)."""
    return method.build(np.asarray(1.0, method.dtype), np.asarray(0.0, method.dtype))


def _parts_us(engine, w, theta, z, repeats: int) -> dict:
    """F's parts at one sample (see the module docstring)."""
    from jaxcal.models.turbofan.physics import cycle
    from jaxcal.models.turbofan.physics.design import design_point
    from jaxcal.models.turbofan.physics.evaluation import residual_fn

    d, dp = engine.design, engine.point
    effects = np.zeros(cycle.NUM_EFFECTS)

    def residual(z, w, th):
        return residual_fn(z, (d, dp, w, th, effects))

    def unrolled(z, w, th):
        one = lambda zz: cycle.balance(d, dp, w, th, effects, zz, unroll=True)[0]  # noqa: E731
        return jax.vmap(one)(z[None])[0]

    args = [(z, w, theta)]
    return {
        "residual_us": _median_us(jax.jit(residual), args, repeats),
        "residual_unrolled_us": _median_us(jax.jit(unrolled), args, repeats),
        "jacobian_us": _median_us(jax.jit(jax.jacfwd(residual)), args, repeats),
        "design_point_us": _median_us(jax.jit(lambda: design_point(d)), [()], repeats),
    }


def main(argv: list[str]) -> int:
    args = dict(a.split("=", 1) for a in argv)
    data = args.get("data", "data/cmapss.h5")
    runs = {
        "CLAC": args.get("absolute", "runs/cmapss-clac-surrogate-s0-absolute"),
        "CLAC-inc": args.get("feedback", "runs/cmapss-clac-physics-inc-s0"),
    }
    repeats = int(args.get("repeats", 300))
    models = Path(args.get("models", "results/paper/models/ds1"))
    suite = Suite(data, runs, SuiteConfig(), models)
    units = suite.test_units()
    out = {"data": data, "runs": runs, "repeats": repeats}
    out.update(engine_numbers(suite, units, repeats))
    names = ["UKF", "CLAC", "CLAC-inc"]
    if (models / "clac-gate.json").is_file():
        names.append("CLAC-gate")
    for name in names:  # as the paper's latency steps measure them
        out[name] = suite.latency(name, repeats=repeats, seed=0)
        method = suite.method(name)
        keyed = measure_latency(
            method, units, repeats=repeats, calibrator=_perturbable(method)
        )
        out[name]["perturbable_form_median_s"] = keyed["median_s"]
        out[name]["deployed_vs_scored_max_abs_theta_diff"] = _deployed_vs_scored(
            method, units
        )
    for name in names[1:]:
        out[f"ratio_ukf_over_{name}"] = out["UKF"]["median_s"] / out[name]["median_s"]
        out[f"perturbable_form_ratio_ukf_over_{name}"] = (
            out["UKF"]["perturbable_form_median_s"]
            / out[name]["perturbable_form_median_s"]
        )
    text = json.dumps(out, indent=1)
    print(text)
    if "out" in args:
        Path(args["out"]).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
