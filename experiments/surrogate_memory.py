"""Why a model with memory trains on its own step, not on the surrogate D (issue 27).

    python experiments/surrogate_memory.py [out=results/policy_any_model]

D learns ``x_{t+1} = D(w_{t+1}, x_t, theta_{t+1})``: the next outputs from the last
*measured* ones. A model with memory carries its state itself. The measurement: the
DC motor of ``experiments/unseen_models.py`` (state: the speed), 12 units simulated
as in the study, D fitted on the labelled transitions of units 1-9 (as the training
job would on simulated units), scored one step ahead on units 10-12, per output in
units of the output's noise std, in two observation set-ups:

* ``speed, current``: the state is an output, measured with noise; D reads it back
  from a noisy reading, the model's own step carries it;
* ``current``: the state is hidden.

The model's own step, run along each unit with the true theta, is the reference: its
error is the noise alone (1.0 in these units). Writes ``<out>/surrogate_memory.json``.
"""

from __future__ import annotations

import json
import os
import sys

import jax
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)


def main(argv: list[str]) -> int:
    opts = {"out": "results/policy_any_model"}
    for token in argv:
        key, _, value = token.partition("=")
        if key not in opts:
            print(f"usage: surrogate_memory.py [out=DIR]; got {token!r}")
            return 2
        opts[key] = value
    jax.config.update("jax_enable_x64", True)
    from unseen_models import NOISE, _simulate, make_fleet, motor_model

    from jaxcal.surrogate.fit import fit_surrogate, make_transitions, surrogate_errors
    from jaxcal.training.config import _DEFAULT_SURROGATE

    model = motor_model()
    fleet = make_fleet("motor")
    units = sorted(fleet.unit.unique())
    w_cols, theta_cols = list(model.condition_names), list(model.parameter_names)
    arrays = {
        k: np.stack([fleet[fleet.unit == u][cols].to_numpy() for u in units])
        for k, cols in (
            ("w", w_cols),
            ("x", list(model.output_names)),
            ("theta", theta_cols),
        )
    }
    clean = np.stack(
        [
            _simulate(model, arrays["w"][i], arrays["theta"][i])
            for i in range(len(units))
        ]
    )
    noise = np.array([NOISE["motor"][o] for o in model.output_names])
    mask = np.ones(arrays["w"].shape[:2], bool)
    train, test = slice(0, 9), slice(9, 12)
    report = {
        "model": "motor (experiments/unseen_models.py)",
        "noise_std": dict(zip(model.output_names, noise.tolist(), strict=True)),
        "own_step_error_over_noise": {
            o: float(
                np.sqrt(np.mean((arrays["x"][test, 1:, i] - clean[test, 1:, i]) ** 2))
                / noise[i]
            )
            for i, o in enumerate(model.output_names)
        },
        "surrogate": {},
    }
    for name, cols in (("speed, current", [0, 1]), ("current", [1])):
        x = arrays["x"][..., cols].astype(np.float32)
        w = arrays["w"].astype(np.float32)
        theta = arrays["theta"].astype(np.float32)
        transitions = make_transitions(w[train], x[train], theta[train], mask[train])
        params, _ = fit_surrogate(jax.random.key(0), transitions, _DEFAULT_SURROGATE)
        err = surrogate_errors(params, w[test], x[test], theta[test], mask[test])
        outs = [model.output_names[c] for c in cols]
        report["surrogate"][name] = {
            "one_step_error_over_noise": dict(
                zip(
                    outs,
                    (np.asarray(err["one_step_rmse"]) / noise[cols]).tolist(),
                    strict=True,
                )
            ),
            "free_run_error_over_noise": dict(
                zip(
                    outs,
                    (np.asarray(err["free_run_rmse"]) / noise[cols]).tolist(),
                    strict=True,
                )
            ),
        }
    os.makedirs(opts["out"], exist_ok=True)
    path = os.path.join(opts["out"], "surrogate_memory.json")
    with open(path, "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
