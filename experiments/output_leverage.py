"""Which sensor faults a filter can tell from a parameter change, per model of the
policy study (issue 41, item 3).

A fault on output k (a bias, a drift, a gain error) moves the whitened innovation
along e_k. The part of e_k in the span of the whitened Jacobian A = J / sigma (the
outputs' sensitivities to the calibrated parameters) is what some change of theta
would also produce; only the remainder (I - H) e_k, with H = A (A^T A)^-1 A^T, is
evidence of a fault. Its share of the fault is 1 - h_k, with h_k = H_kk the
output's leverage (Cook & Weisberg 1982, "Residuals and Influence in Regression",
§2.2). An output of leverage 1 (as every output is where the outputs are no more
than the parameters) carries no such evidence at a single row: there a filter can
only hold still under a fault if it assumes the parameters move slowly, and then it
holds still under a parameter change of the same shape too.

    python experiments/output_leverage.py [cases=heat_exchanger,pump,fan,motor,reactor]
        [rows=10] [out=results/policy_robust/leverage.json]

Static models: the leverage at ``rows`` rows spread over the study's fleet (seed 0)
at their true parameters. Models with memory: the outputs are counted against the
parameters only (their one-row Jacobian runs through the state).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from policy_any_model import _case  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Options:
    """The script's ``key=value`` options (module docstring)."""

    cases: str = "heat_exchanger,pump,fan,motor,reactor"
    rows: int = 10
    out: str = "results/policy_robust/leverage.json"


def leverage(jac: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """``[S]`` each output's leverage ``diag(A pinv(A))`` of the whitened Jacobian
    ``A = jac / sigma`` (``jac`` ``[S, P]``)."""
    a = jac / sigma[:, None]
    return np.clip(np.diag(a @ np.linalg.pinv(a)), 0.0, 1.0)


def case_leverage(name: str, rows: int) -> dict:
    import jax
    import jax.numpy as jnp

    import jaxcal

    spec, fleet, theta, noise = _case(name, 0)
    model = jaxcal.models.load(spec)
    outputs = list(model.output_names)
    entry = {
        "outputs": outputs,
        "parameters": theta,
        "num_outputs": len(outputs),
        "num_parameters": len(theta),
    }
    if model.is_stateful:
        entry["note"] = "model with memory: outputs counted against parameters"
        entry["leverage"] = None
        return entry
    idx = jnp.asarray(model.parameter_index(theta))
    sigma = np.array([noise[o] for o in outputs], float)
    picks = np.linspace(0, len(fleet) - 1, rows).astype(int)
    w_all = fleet[list(model.condition_names)].to_numpy(float)[picks]
    th_all = fleet[list(model.parameter_names)].to_numpy(float)[picks]
    found = []
    for w, th in zip(w_all, th_all, strict=True):  # a few rows: host loop
        full = jnp.asarray(th)

        def outputs_at(t, w=w, full=full):
            return model.evaluate(jnp.asarray(w), full.at[idx].set(t))[0]

        jac = np.asarray(jax.jacfwd(outputs_at)(full[idx]))
        found.append(leverage(jac, sigma))
    found = np.asarray(found)
    entry["leverage"] = {
        "mean": found.mean(0).round(3).tolist(),
        "min": found.min(0).round(3).tolist(),
        "max": found.max(0).round(3).tolist(),
    }
    return entry


def main(argv: list[str]) -> int:
    import jax

    from jaxcal.settings import parse_overrides

    jax.config.update("jax_enable_x64", True)
    opts = parse_overrides(argv, Options())
    result = {c: case_leverage(c, opts.rows) for c in opts.cases.split(",")}
    os.makedirs(os.path.dirname(opts.out) or ".", exist_ok=True)
    with open(opts.out, "w") as f:
        json.dump(result, f, indent=1)
    for name, entry in result.items():
        lev = entry["leverage"]
        pairs = zip(entry["outputs"], (lev or {}).get("mean", []), strict=False)
        shown = entry.get("note") or ", ".join(f"{o} {m:.2f}" for o, m in pairs)
        print(
            f"{name}: {entry['num_outputs']} outputs, {entry['num_parameters']} "
            f"parameters; leverage {shown}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
