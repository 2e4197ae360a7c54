"""The ``final.json`` of a training run: what ran, how fast, and how the kept policy
scores.

:func:`final_report` gathers the run's identity (agent, dynamics, preset, seed, data,
model, parameters, test units), the selection (``budget.select`` and the chunk kept),
the test scores of the kept policy, the validation scores of the kept chunk and
of the last scored one, the counters, the training time and
throughput (:func:`throughput`), the surrogate's report and the time to target
(:func:`jaxcal.training.stages.uncertainty.time_to_target`). The band's coverage and
what was simulated are added by the pipeline.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

from jaxcal.training.components import uses_filter
from jaxcal.training.config import TrainConfig
from jaxcal.training.data.calibration import CalibrationData
from jaxcal.training.kept_policy import KeptPolicy
from jaxcal.training.stages.uncertainty import time_to_target


def throughput(records: list[dict]) -> dict:
    """updates/s and env steps/s over the run's chunks, compile chunks excluded."""
    timed = [r for r in records if not r.get("includes_compile")] or records
    seconds = sum(r["chunk_seconds"] for r in timed)
    if not timed or seconds <= 0:
        return {"updates_per_s": None, "env_steps_per_s": None}
    return {
        "updates_per_s": sum(r["updates_per_s"] * r["chunk_seconds"] for r in timed)
        / seconds,
        "env_steps_per_s": sum(r["env_steps_per_s"] * r["chunk_seconds"] for r in timed)
        / seconds,
    }


def training_gain(
    records: list[dict], selected: int, cfg: TrainConfig, start: dict | None = None
) -> dict:
    """What training added to its untrained start, on the selection's score
    (``budget.select``: lower is better): the start's (chunk 0, scored in the
    training for an actor with a prior; else ``start``, the untrained actor's
    ``val_*`` scores measured after it with ``budget.score_random_start``), the
    kept chunk's and the best trained chunk's, ``ratio`` kept / start (1.0: the
    start kept) and ``start_is``, what the untrained policy is. Without a score
    of the start: ``{"start_is", "scored": False}``."""
    key = (
        "val_sim_theta_rmse"
        if cfg.budget.select == "sim_theta"
        else ("val_tracking_rmse_norm")
    )
    prior = uses_filter(cfg.env) and bool(cfg.env.filter_gain)  # agent_config's
    start_is = "the filter's step" if prior else "a randomly initialised actor"
    scores = {r["step"]: r[key] for r in records if key in r}
    if 0 not in scores and start and key in start:
        scores[0] = start[key]
    if 0 not in scores:
        return {"start_is": start_is, "scored": False}
    trained = {k: v for k, v in scores.items() if k > 0}
    best_chunk = min(trained, key=trained.get) if trained else None
    kept = scores.get(selected, scores[0])
    return {
        "key": key,
        "start": scores[0],
        "kept": kept,
        "ratio": kept / scores[0] if 0 < scores[0] < math.inf else None,
        "best_trained_chunk": best_chunk,
        "best_trained": None if best_chunk is None else trained[best_chunk],
        "kept_start": selected == 0,
        "start_is": start_is,
        "scored": True,
    }


def with_tuning(gain: dict, tuned: dict | None) -> dict:
    """``gain`` (:func:`training_gain`) once ``tune`` kept a tuned policy: its
    selection score is the kept one where both score theta on the simulated
    selection units (``budget.select=sim_theta``); else ``gain`` unchanged."""
    if not gain or not tuned or not tuned["improved"]:
        return gain
    if gain.get("key") != "val_sim_theta_rmse":  # also an unscored start
        return gain
    kept = tuned["selection_theta_rmse_after"]
    ratio = kept / gain["start"] if gain["start"] > 0 else None
    return {**gain, "kept": kept, "ratio": ratio, "kept_start": False, "tuned": True}


def _last_val(records: list[dict]) -> dict:
    """The validation scores of the last scored chunk (``{}``: none scored)."""
    scored = (r for r in reversed(records) if any(k.startswith("val_") for k in r))
    last = next(scored, None)
    if last is None:
        return {}
    return {"chunk": last["step"]} | {
        k[4:]: v for k, v in last.items() if k.startswith("val_")
    }


def final_report(
    cfg: TrainConfig,
    run_dir: Path,
    path: Path,
    data: CalibrationData,
    kept: KeptPolicy,
    test: dict,
    surrogate_report: dict | None,
    target: float | None,
    wall_start: float,
) -> dict:
    """The ``final.json`` dict of a run (the band and the simulations not yet in it).

    Args:
        cfg: the run's config; run_dir: its folder; path: its data file.
        data: the run's data.
        kept: the trained and kept policy.
        test: the kept policy's scores on the test units.
        surrogate_report: the surrogate's fit report (``None``: no surrogate).
        target: the time to target's test theta RMSE (``None``: not measured).
        wall_start: the session's ``time.perf_counter()`` at its start.
    """
    policy = kept.result
    records = policy.records
    val_record = next((r for r in records if r["step"] == kept.selected_step), {})
    return {
        "run": str(run_dir),
        "agent": cfg.agent_name,
        "dynamics": cfg.dynamics,
        "preset": cfg.preset,
        "seed": cfg.seed,
        "data": str(path),
        "model": data.problem.model.name,
        "theta_names": list(data.problem.theta_names),
        "test_units": data.info["units"]["test"],
        "select": cfg.budget.select if kept.select else "last",
        "policy": cfg.budget.policy
        if hasattr(policy.runner.agent_state, "target_actor_params")
        else "online",
        "selected_chunk": kept.selected_step,
        "test": test,
        # the last chunk's validation scores, not a test pass of its own (one
        # more run over the test units)
        "val_last": _last_val(records),
        "val_selected": {
            k[4:]: v for k, v in val_record.items() if k.startswith("val_")
        },
        "training_gain": training_gain(
            records, kept.selected_step, cfg, kept.start_scores
        ),
        "chunks": policy.chunks_done,
        "stopped_early": policy.stopped_early,
        "env_steps": int(policy.runner.env_steps),
        "num_updates": int(policy.runner.num_updates),
        "train_seconds": float(sum(r["chunk_seconds"] for r in records)),
        **throughput(records),
        "session_wall_seconds": time.perf_counter() - wall_start,
        "surrogate": surrogate_report,
        **time_to_target(records, target),
    }
