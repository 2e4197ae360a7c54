"""The output-error lever on its own: the thermal model's records diagnosed by the
one-step (filtered-state) diagnosis of before issue 24 and by the output-error one.

    python experiments/loop_output_error.py write out=DIR [seeds=8]   # the records
    PYTHONPATH=<checkout of before> python experiments/loop_output_error.py old out=DIR
    python experiments/loop_output_error.py new out=DIR

``write`` draws records of the thermal model as the robust study does
(:mod:`robust_scenario`, sizes at 5x each record's detectability size) and stores
them as Parquet with their truth (in ``data/loop_output_error/``, not committed);
``old`` runs a checkout from before issue 24 on
them (its diagnosis filtered the states with the UKF and worked on the one-step
residual; the thermal model is defined here from its equations, as that checkout
has no ``thermal`` model); ``new`` runs this one. Each writes ``<mode>.json``;
``compare`` prints the table (results/loop/robust/levers/output_error/).
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np

KINDS = ("none", "sensor_bias", "sensor_drift", "parameter")
RECORDS = "data/loop_output_error"  # generated records (not committed)


def _thermal():
    """The two-mass heated body (jaxcal/models/thermal.py), for any checkout."""
    import jax.numpy as jnp
    import jax.scipy.linalg as jsl

    from jaxcal.model import Model

    def steady(w, th):
        shell = w[1] + w[0] * th[0]
        return jnp.stack([shell + w[0] * th[1], shell])

    def step(z, w, th):
        r_sa, r_cs, c_core, c_shell = th[0], th[1], th[2], th[3]
        a = jnp.array(
            [
                [-1 / (r_cs * c_core), 1 / (r_cs * c_core)],
                [1 / (r_cs * c_shell), -(1 / r_cs + 1 / r_sa) / c_shell],
            ]
        )
        z_ss = steady(w, th)
        z2 = z_ss + jsl.expm(a * 60.0) @ (z - z_ss)
        return z2, jnp.stack([z2[0], z2[1], (z2[1] - w[1]) / r_sa])

    return Model.from_step(
        step, init_state=steady, states={"core": "K", "shell": "K"},
        conditions={"power": "W", "ambient": "K"},
        parameters={"R_sa": (0.02, 0.01, 0.03, "K/W"),
                    "R_cs": (0.01, 0.005, 0.02, "K/W"),
                    "C_core": (2.0e5, 1.0e5, 4.0e5, "J/K"),
                    "C_shell": (5.0e4, 2.5e4, 1.0e5, "J/K")},
        outputs={"T_core": "K", "T_shell": "K", "q_loss": "W"}, name="thermal",
        condition_range=([0.0, 250.0], [3000.0, 320.0]),
    )  # fmt: skip


def write(out: str, seeds: int) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import loop_robust as lr
    import robust_scenario as rs

    from jaxcal.models import load

    sm, model = rs.STUDY_MODELS["thermal"], load("thermal")
    cfg = lr.RobustConfig(multiples=(5.0,), seed=7)
    loop = lr.loop_config(cfg)
    truth = []
    for kind in KINDS:
        for seed in range(seeds):
            rng = np.random.default_rng([7, KINDS.index(kind), seed])
            setting = rs.draw(sm, rng)
            record_seed = int(rng.integers(2**31))
            target, size, name = "", 0.0, ""
            if kind != "none":
                target, sign, s1 = lr._target(model, sm, cfg, loop, kind, setting,
                                              record_seed, rng)  # fmt: skip
                size = 5.0 * sign * s1
                name = lr.kind_of(model, kind).candidate_name(target)
            data, _, _ = rs.make_record(model, sm, setting, kind, target, size,
                                        record_seed)  # fmt: skip
            frame = data.to_frame() if hasattr(data, "to_frame") else None
            if frame is None:
                import pandas as pd

                frame = pd.DataFrame(data.w, columns=list(data.condition_names))
                for j, s in enumerate(data.output_names):
                    frame[s] = data.x[:, j]
                frame["unit"], frame["time"] = data.unit, data.time
            path = os.path.join(RECORDS, f"{kind}_{seed}.parquet")
            frame.to_parquet(path)
            truth.append({"file": path, "kind": kind, "name": name,
                          "carriers": list(setting.carriers)})  # fmt: skip
            print(path, name, flush=True)
    with open(os.path.join(RECORDS, "truth.json"), "w") as f:
        json.dump(truth, f, indent=1)


def run(out: str, mode: str) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    import pandas as pd

    from jaxcal.data.readers import read_dataset
    from jaxcal.diagnosis.pipeline import diagnose

    model = _thermal()
    with open(os.path.join(RECORDS, "truth.json")) as f:
        truth = json.load(f)
    rows = []
    for t in truth:
        data = read_dataset(pd.read_parquet(t["file"]), model)
        res = diagnose(data, model, ("R_sa",))
        added = [a for a in res.added if a != "discrepancy"]
        rows.append({**t, "verdict": res.verdict, "added": added,
                     "confounded": list(res.confounded)})  # fmt: skip
        print(mode, t["kind"], t["name"], res.verdict, added, flush=True)
    with open(os.path.join(out, f"{mode}.json"), "w") as f:
        json.dump(rows, f, indent=1)


def compare(out: str) -> str:
    lines = ["| kind | records | one-step (before): named / alarm | output error: "
             "named / alarm |", "|---|---|---|---|"]  # fmt: skip
    runs = {}
    for mode in ("old", "new"):
        with open(os.path.join(out, f"{mode}.json")) as f:
            runs[mode] = json.load(f)
    for kind in KINDS:
        cells = []
        for mode in ("old", "new"):
            rs_ = [r for r in runs[mode] if r["kind"] == kind]
            if kind == "none":
                cells.append(
                    f"– / {np.mean([r['verdict'] != 'none' for r in rs_]):.2f}"
                )
            else:
                named = np.mean([r["added"] == [r["name"]] or (
                    r["verdict"].startswith("confounded")
                    and r["name"] in r["confounded"]) for r in rs_])  # fmt: skip
                cells.append(f"{named:.2f} / –")
        n = sum(r["kind"] == kind for r in runs["new"])
        lines.append(f"| {kind} | {n} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    mode, *rest = sys.argv[1:]
    opts = dict(a.split("=", 1) for a in rest)
    out = opts.get("out", "results/loop/robust/levers/output_error")
    RECORDS = opts.get("records", RECORDS)
    os.makedirs(out, exist_ok=True)
    os.makedirs(RECORDS, exist_ok=True)
    if mode == "write":
        write(out, int(opts.get("seeds", 8)))
    elif mode in ("old", "new"):
        run(out, mode)
    else:
        print(compare(out))
