"""First / repeat / new-process time of ``jaxcal.calibrate`` (issue 26), as JSON.

For each case (the README's tank, the heat exchanger, the turbofan on NASA C-MAPSS
FD001 units 1-2) and method (UKF, least squares) one child process calls
``jaxcal.calibrate`` twice on the same data (``first``, ``repeat``) and once on the
same rows with one reading changed (``other_rows``: the same shape, screened again),
then a second child process calls it once (``new_process``). Both children share a
persistent compilation cache directory that starts empty, so ``first`` is a
machine's very first call and ``new_process`` what every later process pays. The
ratios are the issue's goals: ``repeat / first <= 0.10``, ``new_process / first <=
0.50``.

Only the public API is used, so the same script times an older checkout (run it with
``PYTHONPATH=<old checkout>``): ``before`` in ``results/bench/compile.json``.

Usage::

    python experiments/bench_compile.py [cases=tank,heat_exchanger,turbofan]
        [methods=ukf,ls] [out=results/bench/compile.json] [label=after]

Progress goes to stderr; the document is printed and, with ``out=``, merged into that
file under ``label``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FD001 = ROOT.parent / "shared" / "data" / "cmapss" / "train_FD001.txt"
CASES = ("tank", "heat_exchanger", "turbofan")
STAGES = {  # JAX's monitoring events -> the stage of a call they time
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "compile_s",
    "/jax/compilation_cache/cache_retrieval_time_sec": "cache_load_s",
}
METHODS = ("ukf", "ls")
NOTES = "<!-- written by hand: kept when the table is rendered again -->\n"


def _tank():
    import jax
    import jax.numpy as jnp
    import numpy as np
    import pandas as pd

    import jaxcal

    def tank(w, theta):
        heat, inflow = w
        leak, loss = theta
        level = inflow / leak
        return jnp.stack(
            [level, 20 + heat / (inflow * (1 + loss)), leak * level * (1 - loss)]
        )

    model = jaxcal.Model.from_function(
        tank, conditions={"heat": "kW", "inflow": "kg/s"},
        parameters={"leak": (1.0, 0.5, 2.0, "1/s"), "loss": (0.1, 0.0, 0.5)},
        outputs={"level": "m", "temp": "degC", "outflow": "kg/s"},
    )  # fmt: skip
    rng = np.random.default_rng(0)
    w = rng.uniform([5.0, 0.5], [30.0, 2.0], (300, 2))
    truth = np.stack([np.linspace(1.0, 1.3, 300), np.full(300, 0.2)], 1)
    x = jax.vmap(tank)(w, truth) + 0.02 * rng.standard_normal((300, 3))
    cols = model.condition_names + model.output_names
    return model, pd.DataFrame(np.hstack([w, x]), columns=cols), {}


def _heat_exchanger():
    import jax
    import numpy as np
    import pandas as pd

    import jaxcal

    model = jaxcal.models.load("heat_exchanger")
    rng = np.random.default_rng(1)
    low, high = (np.asarray(b) for b in model.condition_range)
    units, n = 4, 400
    w = rng.uniform(low, high, (units * n, len(low)))
    theta = np.tile(model.nominal, (units * n, 1))
    evaluate = jax.jit(jax.vmap(lambda w, t: model.evaluate(w, t)[0]))
    x = np.asarray(evaluate(w, theta))
    x = x + 0.01 * np.abs(x).mean(0) * rng.standard_normal(x.shape)
    cols = model.condition_names + model.output_names
    frame = pd.DataFrame(np.hstack([w, x]), columns=cols)
    frame.insert(0, "unit", np.repeat(np.arange(1, units + 1), n))
    return model, frame, {}


def _turbofan():
    import jaxcal
    from jaxcal.precision import enable_x64

    enable_x64()
    return jaxcal.models.load("cmapss"), str(FD001), {"units": (1, 2)}


def child(case: str, method: str, calls: int) -> dict:
    """Time ``calls`` calibrations of ``case`` in this process."""
    import warnings

    import jaxcal

    model, data, extra = globals()[f"_{case}"]()
    if "units" in extra:
        import numpy as np

        from jaxcal.data.readers import read_dataset

        ds = read_dataset(data, model)
        keep = np.isin(ds.unit, extra["units"])
        data = ds.take(np.flatnonzero(keep))
    from jax import monitoring

    spent = {}  # seconds per JAX compile stage in the current call
    monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: spent.__setitem__(name, spent.get(name, 0.0) + secs)
    )
    times, stages, disk = [], [], []
    for call in range(calls):
        spent.clear()
        rows = _other_rows(data) if call == 2 else data
        start = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = jaxcal.calibrate(model, rows, method=method)
        times.append(time.perf_counter() - start)
        stages.append({STAGES[k]: round(v, 2) for k, v in spent.items() if k in STAGES})
        # a program not kept on disk (or unreadable) makes the next process trace
        # again: recorded, since the calibration's own warnings are not shown
        disk += [str(w.message)[:300] for w in caught if _about_disk(w.message)]
        print(f"  {case} {method}: {times[-1]:.2f} s", file=sys.stderr, flush=True)
    return {
        "times": times, "stages": stages, "rows": int(len(result.theta)),
        "disk_warnings": disk,
    }  # fmt: skip


def _other_rows(data):
    """The same rows with one reading moved by a part in 1e7: data of the same
    shape that the process has not seen, so the call screens again (a repeat on the
    same rows reuses the screening, :mod:`jaxcal.calibrators.front.screen_memo`)."""
    import dataclasses

    if hasattr(data, "iloc"):  # a DataFrame: its last column is an output
        data = data.copy()
        data.iloc[0, -1] *= 1 + 1e-7
        return data
    x = data.x.copy()
    x[0, 0] *= 1 + 1e-7
    return dataclasses.replace(data, x=x)


def _about_disk(message) -> bool:
    """Whether a warning is :mod:`jaxcal.calibrators.programs.on_disk`'s."""
    text = str(message)
    return "not kept on disk" in text or "unreadable" in text


def _spawn(case, method, calls, cache_dir) -> dict:
    env = dict(os.environ, JAXCAL_CACHE_DIR=cache_dir, JAX_PLATFORMS="cpu")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    cmd = [sys.executable, __file__, "child", case, method, str(calls)]
    out = subprocess.run(cmd, env=env, check=True, stdout=subprocess.PIPE, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure(case: str, method: str) -> dict:
    with tempfile.TemporaryDirectory(prefix="jaxcal-bench-cache-") as cache:
        both = _spawn(case, method, 3, cache)
        fresh = _spawn(case, method, 1, cache)
    first, repeat, other = both["times"]
    new = fresh["times"][0]
    return {
        "first_s": round(first, 3),
        "repeat_s": round(repeat, 3),
        "other_rows_s": round(other, 3),
        "new_process_s": round(new, 3),
        "repeat_ratio": round(repeat / first, 4),
        "new_process_ratio": round(new / first, 4),
        "rows": both["rows"],
        "disk_warnings": both["disk_warnings"] + fresh["disk_warnings"],
        "stages": {
            "first": both["stages"][0], "repeat": both["stages"][1],
            "other_rows": both["stages"][2], "new_process": fresh["stages"][0],
        },
    }  # fmt: skip


def render(whole: dict) -> str:
    """The Markdown table of every label's figures (before / after)."""
    lines = [
        "# Compile once: first / repeat / new-process time of `jaxcal.calibrate`",
        "",
        "`python experiments/bench_compile.py` (issue 26): seconds of one call; `first`"
        " with an empty compilation cache, `repeat` the same call again in that"
        " process, `new process` a fresh process on the now warm cache. Goals: repeat"
        " <= 10 % and new process <= 50 % of the first. `other rows`: a third call in"
        " the first process on the same rows with one reading changed (the same"
        " shape, rows it has not screened; measured from this stop on).",
        "",
        "| case | code | first s | repeat s | other rows s | new process s |"
        " repeat / first | new process / first |",
        "|---|---|---|---|---|---|---|---|",
    ]
    cases = sorted({case for doc in whole.values() for case in doc})
    for case in cases:
        for label, doc in whole.items():
            if case in doc:
                f = doc[case]
                lines.append(
                    f"| {case} | {label} | {f['first_s']:.2f} | {f['repeat_s']:.2f} | "
                    f"{_seconds(f.get('other_rows_s'))} | {f['new_process_s']:.2f} | "
                    f"{f['repeat_ratio']:.3f} | "
                    f"{f['new_process_ratio']:.3f} |"
                )
    return "\n".join(lines) + "\n"


def _seconds(value) -> str:
    return "–" if value is None else f"{value:.2f}"


def main(argv: list[str]) -> None:
    if argv and argv[0] == "child":
        print(json.dumps(child(argv[1], argv[2], int(argv[3]))))
        return
    opts = dict(a.split("=", 1) for a in argv)
    cases = opts.get("cases", ",".join(CASES)).split(",")
    methods = opts.get("methods", ",".join(METHODS)).split(",")
    doc = {}
    for case in cases:
        for method in methods:
            print(f"{case} / {method}", file=sys.stderr, flush=True)
            doc[f"{case}/{method}"] = measure(case, method)
    print(json.dumps(doc, indent=1))
    if "out" in opts:
        from jaxcal.runs.atomic import write_atomic

        path = Path(opts["out"])
        whole = json.loads(path.read_text()) if path.exists() else {}
        whole.setdefault(opts.get("label", "after"), {}).update(doc)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, json.dumps(whole, indent=1) + "\n")
        page = path.with_suffix(".md")
        kept = page.read_text().partition(NOTES)[2] if page.exists() else ""
        write_atomic(page, render(whole) + (f"\n{NOTES}{kept}" if kept else ""))


if __name__ == "__main__":
    main(sys.argv[1:])
