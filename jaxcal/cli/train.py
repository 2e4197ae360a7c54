"""Command line: train a calibration policy (the product's main job).

Usage::

    python -m jaxcal.train dataset=cmapss [agent=clac|lac|sac]
        [dynamics=surrogate|physics] [preset=default|absolute|smoke|paper] [seed=0]
        [name=<run>] [key=value ...]
    python -m jaxcal.train dataset=ncmapss path=N-CMAPSS_DS02-006.h5 \
        theta=HPT_eff_mod,LPT_eff_mod,LPT_flow_mod
    python -m jaxcal.train model=<name | module:attr | path.py:attr> \
        data=<file .csv/.parquet/.h5/.txt> theta=<names> [outputs=<names>] \
        [test_units=<ids>] [val_units=<ids>] [dynamics=surrogate|physics]

Any :class:`jaxcal.Model`, static or with hidden states, trains the same way (a
model with memory on its own step, ``dynamics=physics``: the surrogate cannot carry
its states): the file's columns are named as the model's conditions and outputs
(optional ``unit``, ``time``, ``split`` and true-parameter columns). Without a
``split`` column whole units are held out: the last ~20 % for test (``test_units=``
chooses), ~15 % of the rest for validation (``val_units=``). ``dynamics=surrogate``
needs the true parameters of the training units; ``dynamics=physics`` runs the model
itself (float64 only for a model that needs it, which this command enables).

Generates the data set if its file is missing, fits the surrogate D (``dynamics=
surrogate``; the default preset trains on the model itself), trains the policy
with progress (steps, updates/s, cost, validation theta RMSE), writes
``runs/<name>/`` (resolved ``config.json``, ``metrics.jsonl``, Orbax checkpoints,
``final.json``, the kept policy's 90 % theta band ``uncertainty.json``) and prints
the test units' theta RMSE and tracking RMSE, the band's test coverage and, with
``budget.target_theta_rmse`` set (``dataset=cmapss``: 2.5e-4), the job's wall time
to the first scoring whose validation theta RMSE reached it. Rerunning
the same command resumes from the last checkpoint; a run folder made with a different
config is an error. Every check of the config and the data (path given, file readable,
theta and sensor names, unit splits, run folder writable) runs before the run folder is
created: a start that fails (exit code 2) leaves nothing behind, and the corrected
command runs. ``name=`` is one folder name inside ``output.runs_dir``
(``name=../x``, an absolute name or one with a path separator: exit code 2). A second
training of a run in use exits 2 with who holds it (the lock dies with its process).
The run folder keeps a copy of a ``model=file.py:attr`` file, which loading the run
uses (a resume refuses a model file changed since the run started). Every field of
:class:`jaxcal.training.config.TrainConfig` can be set with ``key=value`` (dotted
for nested fields: ``agent.actor_lr=1e-4``, ``runner.num_envs=32``,
``budget.num_chunks=100``, ``surrogate.fit.num_epochs=20``); ``name=`` is
``output.name=``. An unknown key is an error that lists the valid keys (exit code 2).
"""

from __future__ import annotations

import json
import os
import sys
import time

from jaxcal.cache import enable_compilation_cache
from jaxcal.cli.args import parse_command_line
from jaxcal.precision import enable_x64
from jaxcal.training.config import TrainConfig, resolve_config
from jaxcal.training.scoring.trajectories import describe_units

USAGE = (
    "usage: python -m jaxcal.train dataset=cmapss|agtf30|ncmapss|tiny | "
    "model=NAME|MODULE:ATTR|FILE.py:ATTR data=FILE [agent=clac|lac|sac] "
    "[dynamics=surrogate|physics] [preset=default|absolute|smoke|paper] "
    "[seed=N] [name=RUN] "
    "[path=FILE.h5] [theta=A,B] [outputs=A,B] [test_units=1,2] [val_units=3] "
    "[key=value ...]"
)


def parse_args(argv: list[str]) -> TrainConfig:
    """The resolved config of a command line (``name=`` means ``output.name=``).

    Raises:
        ValueError: see :func:`jaxcal.training.config.resolve_config`.
    """
    tokens = [
        "output.name=" + t.partition("=")[2] if t.startswith("name=") else t
        for t in argv
    ]
    return resolve_config(tokens)


def format_final(final: dict) -> str:
    """The closing summary printed at the end of a run."""
    test = final["test"]
    theta = "no true parameters to score"
    if test["theta_rmse"] is not None:
        theta = (
            f"theta RMSE {test['theta_rmse']:.3e} ("
            + ", ".join(f"{k} {v:.3e}" for k, v in test["theta_rmse_per_param"].items())
            + ")"
        )
    last = final.get("val_last") or {}
    lines = [
        f"run {final['run']}: {final['agent']} on {final['dynamics']}, "
        f"{final['chunks']} chunks, {final['num_updates']:,} updates, "
        f"{final['env_steps']:,} env steps",
        f"test units {describe_units(final['test_units'])}: {theta}",
        f"tracking RMSE {test['tracking_rmse_norm']:.4f} (normalised); in sensor "
        "units: "
        + ", ".join(f"{k} {v:.4g}" for k, v in test["tracking_rmse_units"].items()),
        f"kept policy: {final['policy']} actor of chunk {final['selected_chunk']} "
        f"(select={final['select']})"
        + (
            f"; last scored chunk ({last['chunk']})'s validation theta RMSE "
            f"{last['theta_rmse']:.3e}"
            if last.get("theta_rmse") is not None
            else ""
        ),
    ]
    gain = final.get("training_gain") or {}
    if gain:
        lines.append(_gain_line(gain))
    if final.get("updates_per_s"):
        lines.append(
            f"throughput {final['updates_per_s']:.0f} updates/s, "
            f"{final['env_steps_per_s']:,.0f} env steps/s; policy training "
            f"{final['train_seconds']:.0f} s"
        )
    target = final.get("target_theta_rmse")
    if target is not None:
        reached = final.get("time_to_target_s")
        lines.append(
            f"time to target (validation theta RMSE <= {target:.2e}): "
            + (
                f"{reached:.0f} s of job wall time (chunk "
                f"{final['time_to_target_chunk']})"
                if reached is not None
                else f"not reached in {final.get('target_scorings', 0)} scorings"
            )
        )
    if final.get("test_coverage90") is not None:
        band = final["uncertainty"]
        lines.append(
            f"90 % theta band: test coverage {final['test_coverage90']:.3f} "
            f"({band['num_buckets']} buckets fitted on val units "
            f"{describe_units(band['val_units'])}, {band['file']})"
        )
    if final.get("wall_seconds") is not None:
        total = final.get("wall_seconds_total", final["wall_seconds"])
        sessions = final.get("sessions", 1)
        lines.append(
            f"wall time {final['wall_seconds']:.0f} s"
            + (f" ({total:.0f} s over {sessions} sessions)" if sessions > 1 else "")
        )
    return "\n".join(lines)


def _gain_line(gain: dict) -> str:
    """One plain line: did training improve on the untrained start?"""
    if not gain.get("scored", True):
        how = (  # a random actor's start is scored on request only
            " (budget.score_random_start=true scores it: one more validation pass)"
            if gain["start_is"] == "a randomly initialised actor"
            else ""
        )
        return f"the untrained start ({gain['start_is']}) was not scored{how}"
    what = gain["key"].removeprefix("val_").replace("_", " ")
    start_is = gain.get("start_is", "the filter's step")  # older runs: the filter's
    if gain["kept_start"]:
        best = gain["best_trained"]
        return (
            f"training did not improve on its untrained start ({start_is}): "
            f"the run keeps the start (validation {what} {gain['start']:.3e}"
            + (
                ""
                if best is None
                else f"; the best trained chunk, {gain['best_trained_chunk']}, "
                f"{best:.3e}"
            )
            + ")"
        )
    how = " (tuned by gradient through the filter)" if gain.get("tuned") else ""
    r = gain["ratio"]  # a random start's: far below 0.01
    ratio = "" if r is None else f" ({r:.2f}x)" if r >= 0.01 else f" ({r:.1e}x)"
    # a random start is no candidate: the kept chunk may score worse than it
    verdict = "did not improve" if r is not None and r >= 1 else "improved"
    return (
        f"training {verdict} on its untrained start ({start_is}){how}: validation "
        f"{what} {gain['start']:.3e} -> {gain['kept']:.3e}{ratio}"
    )


def _previous_final(path: str) -> dict:
    """The ``final.json`` an earlier session of this run left, or ``{}``."""
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


def _model_needs_x64(spec: str) -> bool:
    """Whether the run's model needs float64, asked before it is loaded where
    possible: the turbofans (an N-CMAPSS file's engine, or named) do; any other model
    is loaded and asked (a bad spec is reported by the training job)."""
    # the registry loads only for model=
    from jaxcal.models import load

    if spec in ("", "cmapss", "agtf30"):
        return True
    try:
        return load(spec).x64
    except ValueError:
        return False


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 2 bad arguments, 1 failure)."""
    start = time.perf_counter()
    cfg, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if code is not None:
        return code

    # the training job loads after the arguments are checked
    from jaxcal.runs.folder import FINAL_FILE
    from jaxcal.training.pipeline import GenerationError, run_training

    # a missing data file is generated with the engine, whose solve compiles in ~45 s
    enable_compilation_cache()
    if cfg.dynamics == "physics" and _model_needs_x64(cfg.model):
        enable_x64()  # before the model loads: its constants take the float dtype

    # A resumed run's wall time is spread over its sessions: keep the running total.
    previous = _previous_final(
        os.path.join(cfg.output.runs_dir, cfg.run_name, FINAL_FILE)
    )
    before = previous.get("wall_seconds_total", previous.get("wall_seconds", 0.0))

    def finish(final: dict) -> dict:  # written once, under the run's lock
        final["wall_seconds"] = time.perf_counter() - start
        final["sessions"] = previous.get("sessions", 1 if previous else 0) + 1
        final["wall_seconds_total"] = final["wall_seconds"] + before
        return final

    try:
        final = run_training(
            cfg, clock=lambda: before + time.perf_counter() - start, finish=finish
        )
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except GenerationError as err:  # the data generation itself failed: exit 1
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(format_final(final))
    return 0


if __name__ == "__main__":
    sys.exit(main())
