"""The policy of a training run: trained with its deployable checkpoints, and the
one the run keeps.

:func:`train_kept_policy` runs the host loop (:func:`jaxcal.training.stages.policy.
train_policy`) with the run's budget. Besides the runner checkpoints, every
checkpoint step saves the deployable
:class:`~jaxcal.calibrators.methods.policy.calibrator.
PolicyParams` under ``policy/``. With selection on (``budget.select=val_tracking``
and validation units, or ``budget.select=sim_theta``) each scored chunk that beats
the best so far saves its policy under ``policy_best/`` (one kept), and that policy
is the run's selected one; otherwise the last policy is.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax

from jaxcal.calibrators.methods.policy.calibrator import PolicyParams
from jaxcal.envs.tracking import EnvParams
from jaxcal.runs.checkpoint import Checkpointer
from jaxcal.runs.folder import POLICY_BEST_DIR, POLICY_DIR
from jaxcal.training.config import TrainConfig
from jaxcal.training.runner import initial_agent_state
from jaxcal.training.scoring.policy import PolicyScoring
from jaxcal.training.stages.policy import ChunkScoring, PolicyResult, train_policy
from jaxcal.typedefs import PRNGKey


class KeptPolicy(NamedTuple):
    """What :func:`train_kept_policy` trained and kept.

    Attributes:
        result: the host loop's :class:`~jaxcal.training.stages.policy.PolicyResult`.
        last: the deployable policy of the last chunk.
        selected: the policy the run keeps (``last`` without selection).
        selected_step: its chunk.
        select: whether selection was on.
        start_scores: the untrained policy's validation scores (``val_*``) where
            the training did not score its chunk 0 (an actor without a prior: a
            random network, scored after the training for ``final.json``'s
            ``training_gain`` with ``budget.score_random_start``); ``None``
            otherwise.
        val_out: the selected policy's run over the validation units, made when
            its chunk was scored in this session (``None``: not kept), for the
            band (:func:`jaxcal.training.stages.uncertainty.band_runs`).
    """

    result: PolicyResult
    last: PolicyParams
    selected: PolicyParams
    selected_step: int
    select: bool
    start_scores: dict | None = None
    val_out: object | None = None


def train_kept_policy(
    cfg: TrainConfig,
    key: PRNGKey,
    run_dir: Path,
    parts,
    train_params: EnvParams,
    scoring: PolicyScoring,
    *,
    has_val: bool,
    target: float | None,
    clock: Callable[[], float],
    wall_start: float,
    log: Callable[[str], None],
) -> KeptPolicy:
    """Trains (or resumes) the run's policy and returns it with the kept one.

    Args:
        cfg: the run's config (budget, runner, output).
        key: the runner's PRNG key.
        run_dir: the run folder.
        parts: the run's components (environment, agent, jitted chunk).
        train_params: the training units' :class:`EnvParams`.
        scoring: the run's :class:`~jaxcal.training.scoring.policy.PolicyScoring`.
        has_val: whether the run has validation units.
        target: the validation theta RMSE of time to target (``None``: not
            reported).
        clock: seconds since the job's start; wall_start: its
            ``time.perf_counter()`` (the time limit counts from it).
        log: where one-line messages go.
    """
    select = (cfg.budget.select == "val_tracking" and has_val) or (
        cfg.budget.select == "sim_theta"
    )
    deadline = (
        None
        if cfg.budget.time_limit_s is None
        else wall_start + cfg.budget.time_limit_s
    )
    keep = cfg.output.max_to_keep
    with (
        Checkpointer(run_dir / POLICY_DIR, max_to_keep=keep) as latest_ckpt,
        Checkpointer(run_dir / POLICY_BEST_DIR, max_to_keep=1) as best_ckpt,
    ):
        save_latest, save_best = _savers(scoring.deployable, latest_ckpt, best_ckpt)
        best_runs: dict = {}  # the best chunk's validation run, made at its scoring

        def on_best(chunk: int, runner) -> None:
            save_best(chunk, runner)
            best_runs.clear()
            best_runs[chunk] = scoring.last_val_out()

        policy = train_policy(
            key,
            parts.env,
            parts.agent,
            parts.train_chunk,
            train_params,
            cfg.runner,
            run_dir,
            num_chunks=cfg.budget.num_chunks,
            eval_every=cfg.budget.eval_every,
            ckpt_every=cfg.budget.ckpt_every,
            deadline=deadline,
            save_buffer=cfg.output.save_buffer,
            max_to_keep=keep,
            scoring=ChunkScoring(
                scorer=scoring.val_scorer,
                best_key="val_sim_theta_rmse"
                if cfg.budget.select == "sim_theta"
                else "val_tracking_rmse_norm",
                on_best=on_best if select else None,
                target=target,
                clock=clock,
                # an actor with a prior works untrained; with num_chunks=0 any
                # actor's untrained policy is scored and kept (a deployable start)
                score_start=getattr(parts.actor, "prior", None) is not None
                or cfg.budget.num_chunks == 0,
                patience=cfg.budget.patience,
            ),
            on_checkpoint=save_latest,
            progress=cfg.output.progress,
            log=log,
        )
        last = scoring.deployable(policy.runner.agent_state)
        selected, selected_step = last, policy.chunks_done
        if select and best_ckpt.latest_step() is not None:
            selected_step = best_ckpt.latest_step()
            selected = best_ckpt.restore(selected_step, last)
    start = None
    if cfg.budget.score_random_start:
        start = _unscored_start(key, parts, scoring, policy.records, log)
    val_out = best_runs.get(selected_step) if select else None
    return KeptPolicy(policy, last, selected, selected_step, select, start, val_out)


def _unscored_start(key, parts, scoring: PolicyScoring, records, log) -> dict | None:
    """The untrained policy's validation scores (``val_*``) where the training
    scored chunks but not chunk 0 (an actor without a prior starts as a random
    network, never a candidate): what the training gained over its start
    (``final.json``'s ``training_gain``) is then measured, at the cost of one
    validation scoring. ``None`` where chunk 0 was scored or nothing is."""
    scored = [r for r in records if any(k.startswith("val_") for k in r)]
    if scoring.val_scorer is None or not scored or scored[0]["step"] == 0:
        return None
    tic = time.perf_counter()
    scores = scoring.val_scorer(initial_agent_state(key, parts.agent))
    log(
        "the untrained start (a randomly initialised actor) scored on the "
        f"validation units in {time.perf_counter() - tic:.1f} s"
    )
    return {f"val_{k}": v for k, v in scores.items()}


def _savers(deployable, latest_ckpt: Checkpointer, best_ckpt: Checkpointer):
    """``(save_latest, save_best)``, both ``(chunk, runner) -> None``: the deployable
    policy of the runner's agent state saved under ``policy/`` / ``policy_best/``."""

    def save_latest(step: int, runner) -> None:
        params = deployable(runner.agent_state)
        latest_ckpt.save(step, jax.device_get(params), wait=True)

    def save_best(step: int, runner) -> None:
        # A chunk re-run after a resume reproduces the policy already saved.
        if step not in best_ckpt.all_steps():
            params = deployable(runner.agent_state)
            best_ckpt.save(step, jax.device_get(params), wait=True)

    return save_latest, save_best
