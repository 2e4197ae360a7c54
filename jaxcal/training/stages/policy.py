"""Stage 2 of a training run: the policy, trained in jitted chunks, logged and saved.

The environment steps and agent updates run inside
:func:`jaxcal.training.runner.make_train_chunk` (one ``jax.jit``, ``lax.scan`` over
iterations, environments vmapped, replay buffer on device); this module is the host loop
around it (STYLE §2.4): per chunk it writes one JSONL record (cost, agent diagnostics,
counters, wall time, updates/s, env steps/s and, every ``eval_every`` chunks, the
validation scores and the job's wall time, and the first crossing of the time to
target), updates a tqdm bar, and saves an Orbax checkpoint every
``ckpt_every`` chunks and after the last one.

Checkpoints hold the whole :class:`~jaxcal.training.runner.RunnerState` (agent, env
states, observations, PRNG key, counters), with the replay buffer unless
``output.save_buffer=false``. With the buffer, a resumed run continues bit for bit as if
it had never stopped; without it, the buffer restarts empty and updates pause until it
holds ``min_buffer_size`` transitions again. Records logged after the last checkpoint
are dropped on resume, since those chunks are run again.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from jaxcal.agents.buffer import init_buffer
from jaxcal.agents.common import Agent
from jaxcal.envs.tracking import Env, EnvParams
from jaxcal.progress import progress_bar
from jaxcal.runs.checkpoint import Checkpointer
from jaxcal.runs.folder import CHECKPOINT_DIR, METRICS_FILE, truncate_metrics
from jaxcal.runs.metrics_log import MetricsWriter
from jaxcal.training.runner import RunnerConfig, RunnerState, init_runner
from jaxcal.typedefs import PRNGKey

# Jitted once per process; env, agent and config are static (hashable) arguments.
_init_runner = jax.jit(init_runner, static_argnums=(1, 2, 4))

# The label-free selection criterion: validation tracking RMSE (normalised).
BEST_KEY = "val_tracking_rmse_norm"

Scorer = Callable[[Any], dict]
"""``scorer(agent_state) -> {"theta_rmse": ..., "tracking_rmse_norm": ...}``."""

# The time to target's score: the validation units' theta RMSE, scored with every
# validation pass anyway (a separate test pass would cost a run over the test units).
TARGET_KEY = "val_theta_rmse"


class PolicyResult(NamedTuple):
    """Outcome of :func:`train_policy`.

    Attributes:
        runner: the final runner state.
        records: every metrics record of the run (earlier sessions included).
        chunks_done: chunks trained in total.
        stopped_early: True when ``time_limit_s`` ended the session.
    """

    runner: RunnerState
    records: list[dict]
    chunks_done: int
    stopped_early: bool


def _saved_fields(runner: RunnerState, save_buffer: bool) -> dict:
    """The runner's fields as a checkpoint holds them (the buffer optional)."""
    return {
        name: getattr(runner, name)
        for name in runner.__dataclass_fields__
        if save_buffer or name != "buffer"
    }


def _checkpoint_item(runner: RunnerState, save_buffer: bool) -> dict:
    """The saved pytree, host copies: copies (not views) make the save independent
    of the next chunk, which donates the device buffers of ``runner``."""
    return jax.tree.map(
        lambda x: (
            x
            if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)
            else np.array(x, copy=True)
        ),
        _saved_fields(runner, save_buffer),
    )


def _restore_runner(
    ckpt: Checkpointer,
    abstract: RunnerState,
    cfg: RunnerConfig,
    env: Env,
    save_buffer: bool,
) -> RunnerState:
    restored = ckpt.restore(None, _saved_fields(abstract, save_buffer))
    if not save_buffer:
        restored["buffer"] = init_buffer(
            cfg.buffer_size, env.observation_size, env.action_size
        )
    return RunnerState(**restored)


class ChunkScoring(NamedTuple):
    """How :func:`train_policy` scores a chunk (every ``eval_every`` chunks and the
    last) and selects the kept one; every field is optional.

    Attributes:
        scorer: validation scores of an agent state, logged as ``val_*``.
        best_key: the record field selection minimises (default: the validation
            tracking RMSE; ``val_sim_theta_rmse``: theta RMSE on simulated units).
        on_best: called as ``on_best(chunk, runner)`` when a scored chunk has the
            lowest ``best_key`` so far (earlier sessions included).
        target: the validation theta RMSE whose first crossing (``val_theta_rmse
            <= target``, earlier sessions included) is logged once, and marked in
            its record as ``time_to_target_s`` / ``time_to_target_chunk``;
            reporting only (selection reads ``best_key``).
        clock: seconds since the job's start (earlier sessions included); stamped
            as ``job_seconds`` on every scored record, after the validation
            scores.
        score_start: also score the untrained policy (chunk 0) and keep it if no
            chunk beats it: an actor with a prior
            (:attr:`~jaxcal.agents.configs._ActorCriticConfig.actor_prior`) is a
            working calibrator before its first update.
        patience: end the session after this many scored chunks in a row that do
            not lower ``best_key`` (``None``: never): a training that does not
            improve on its best, often its untrained start, stops instead of
            spending its whole budget (:func:`_out_of_patience`).
    """

    scorer: Scorer | None = None
    best_key: str = BEST_KEY
    on_best: Callable[[int, RunnerState], None] | None = None
    target: float | None = None
    clock: Callable[[], float] | None = None
    score_start: bool = False
    patience: int | None = None


def train_policy(
    key: PRNGKey,
    env: Env,
    agent: Agent,
    train_chunk: Callable,
    train_params: EnvParams,
    runner_cfg: RunnerConfig,
    run_dir: str | Path,
    *,
    num_chunks: int,
    eval_every: int = 0,
    ckpt_every: int = 1,
    deadline: float | None = None,
    save_buffer: bool = True,
    max_to_keep: int = 2,
    scoring: ChunkScoring = ChunkScoring(),
    on_checkpoint: Callable[[int, RunnerState], None] | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> PolicyResult:
    """Trains (or resumes training) the policy for ``num_chunks`` chunks in total.

    Args:
        key: PRNG key of the runner (agent initialisation, environments, updates).
        env, agent: the tracking environment and the agent.
        train_chunk: the jitted chunk,
            ``jax.jit(make_train_chunk(env, agent, runner_cfg), donate_argnums=0)``.
        train_params: the training units' :class:`EnvParams`.
        runner_cfg: loop sizes.
        run_dir: the run folder (``checkpoints/`` and ``metrics.jsonl`` live there).
        num_chunks: total chunks of the run (earlier sessions included).
        eval_every: chunks between scorings (0: never; the last chunk is always
            scored when a scorer is given).
        ckpt_every: chunks between checkpoints (the last chunk is always saved).
        deadline: ``time.perf_counter()`` value after which the session ends (after
            the chunk that crosses it); ``None``: no limit.
        save_buffer: include the replay buffer in checkpoints.
        max_to_keep: checkpoints kept on disk.
        scoring: the scorings and the selection (:class:`ChunkScoring`).
        on_checkpoint: called as ``on_checkpoint(chunk, runner)`` after each save
            (the pipeline saves the deployable policy there).
        progress: show a tqdm bar.
        log: where one-line messages go.
    """
    run_dir = Path(run_dir)
    with Checkpointer(run_dir / CHECKPOINT_DIR, max_to_keep=max_to_keep) as ckpt:
        start, runner = _start_runner(
            ckpt, run_dir, key, env, agent, train_params, runner_cfg, save_buffer, log
        )
        records = truncate_metrics(run_dir / METRICS_FILE, start)
        # num_chunks=0 with a prior: the untrained policy is scored and kept
        untrained_only = num_chunks == 0 and start == 0 and scoring.score_start
        if start >= num_chunks and not untrained_only:
            return PolicyResult(runner, records, start, False)
        best, reached, last_val = _earlier_marks(records, scoring)
        bar = _progress_bar(num_chunks, start, progress)
        with MetricsWriter(run_dir / METRICS_FILE) as writer, bar:
            if start == 0 and scoring.score_start:  # the untrained policy: a candidate
                record = dict(chunk_seconds=0.0, includes_compile=True)
                record.update(updates_per_s=0.0, env_steps_per_s=0.0)
                reached = _score(record, runner, 0, scoring, reached, log)
                writer.write(0, record)
                records.append({"step": 0, **record})
                best = _select(record, best, 0, runner, scoring)
            chunk, stopped_early = start, False
            for chunk in range(start + 1, num_chunks + 1):
                runner, record = _timed_chunk(
                    train_chunk, runner, train_params, runner_cfg, chunk == start + 1
                )
                scored = chunk == num_chunks or _past(deadline)
                if scored or bool(eval_every and chunk % eval_every == 0):
                    reached = _score(record, runner, chunk, scoring, reached, log)
                writer.write(chunk, record)
                records.append({"step": chunk, **record})
                patience_out = _out_of_patience(records, scoring)
                last = scored or patience_out
                if chunk % ckpt_every == 0 or last:
                    _save(ckpt, chunk, runner, save_buffer, on_checkpoint)
                best = _select(record, best, chunk, runner, scoring)
                last_val = record.get("val_theta_rmse", last_val)
                bar.update(1)
                bar.set_postfix(_postfix(record, last_val), refresh=False)
                if last:
                    stopped_early = _stopped_early(
                        chunk, num_chunks, log, patience_out and scoring.patience
                    )
                    break
        ckpt.wait_until_finished()
    return PolicyResult(runner, records, chunk, stopped_early)


def _start_runner(
    ckpt, run_dir, key, env, agent, train_params, runner_cfg, save_buffer, log
):
    """``(start, runner)``: the runner restored from the latest checkpoint of
    ``run_dir`` (its chunk ``start``), or a new one at ``start = 0``."""
    start = ckpt.latest_step() or 0
    if not start:
        return 0, _init_runner(key, env, agent, train_params, runner_cfg)
    abstract = jax.eval_shape(
        lambda k: init_runner(k, env, agent, train_params, runner_cfg), key
    )
    runner = _restore_runner(ckpt, abstract, runner_cfg, env, save_buffer)
    log(f"resumed from checkpoint {start} of {run_dir / CHECKPOINT_DIR}")
    return start, runner


def _past(deadline: float | None) -> bool:
    """Whether the session's ``deadline`` (a ``time.perf_counter()`` value) has
    passed (never without one)."""
    return deadline is not None and time.perf_counter() >= deadline


def _save(ckpt, chunk: int, runner, save_buffer: bool, on_checkpoint) -> None:
    """The runner checkpoint of ``chunk``, then ``on_checkpoint(chunk, runner)``."""
    ckpt.save(chunk, _checkpoint_item(runner, save_buffer))
    if on_checkpoint is not None:
        on_checkpoint(chunk, runner)


def _stopped_early(chunk: int, num_chunks: int, log, patience=None) -> bool:
    """Whether the session ended before the run's last chunk (said in the log:
    the time limit, or ``patience`` scorings without a better policy)."""
    stopped_early = chunk < num_chunks
    if stopped_early and patience:
        log(
            f"stopped after chunk {chunk} of {num_chunks}: {patience} scored "
            "chunks in a row without a better policy (budget.patience)"
        )
    elif stopped_early:
        log(f"time limit reached after chunk {chunk} of {num_chunks}")
    return stopped_early


def _out_of_patience(records: list[dict], scoring: ChunkScoring) -> bool:
    """Whether the last ``scoring.patience`` scored records (earlier sessions
    included) all fail to lower the best ``best_key`` scored before them."""
    if not scoring.patience:
        return False
    scores = [r[scoring.best_key] for r in records if scoring.best_key in r]
    if len(scores) <= scoring.patience:
        return False
    before = min(scores[: -scoring.patience])
    return min(scores[-scoring.patience :]) >= before


def _earlier_marks(records: list[dict], scoring: ChunkScoring):
    """``(best, reached, last_val)`` of the earlier sessions' records: the lowest
    ``best_key``, whether the target was reached, the last validation theta RMSE."""
    best_key = scoring.best_key
    best = min((r[best_key] for r in records if best_key in r), default=float("inf"))
    reached = any(_reaches(r, scoring.target) for r in records)
    last_val = next(
        (r["val_theta_rmse"] for r in reversed(records) if "val_theta_rmse" in r),
        None,
    )
    return best, reached, last_val


def _progress_bar(num_chunks: int, start: int, progress: bool):
    """The chunks' tqdm bar (off with ``progress=False``)."""
    return progress_bar(
        total=num_chunks,
        initial=start,
        desc="policy",
        unit="chunk",
        disable=not progress,
        dynamic_ncols=True,
    )


def _timed_chunk(train_chunk, runner, train_params, runner_cfg, first: bool):
    """``(runner, record)`` of one chunk: its metrics as scalars, its wall time and
    throughput (``includes_compile`` on a session's first chunk)."""
    updates_before = int(runner.num_updates)
    tic = time.perf_counter()
    runner, metrics = train_chunk(runner, train_params)
    record = {k: np.asarray(v).item() for k, v in jax.device_get(metrics).items()}
    seconds = time.perf_counter() - tic
    record.update(
        chunk_seconds=seconds,
        includes_compile=first,
        updates_per_s=(record["num_updates"] - updates_before) / seconds,
        env_steps_per_s=runner_cfg.num_envs * runner_cfg.num_steps_per_chunk / seconds,
    )
    return runner, record


def _score(record: dict, runner, chunk: int, scoring: ChunkScoring, reached, log):
    """Adds a scored chunk's validation scores and job time to its ``record``;
    returns whether the target is reached (its first crossing logged and
    marked)."""
    if scoring.scorer is not None:
        scores = scoring.scorer(runner.agent_state)
        record.update({f"val_{k}": v for k, v in scores.items()})
    if scoring.clock is not None:
        record["job_seconds"] = scoring.clock()
    if not reached and _reaches(record, scoring.target):
        reached = True
        record["time_to_target_s"] = record.get("job_seconds")
        record["time_to_target_chunk"] = chunk
        log(
            f"validation theta RMSE {record[TARGET_KEY]:.3e} <= target "
            f"{scoring.target:.3e} at chunk {chunk}, "
            f"{record.get('job_seconds') or 0:.0f} s into the job"
        )
    return reached


def _select(record: dict, best: float, chunk: int, runner, scoring: ChunkScoring):
    """The lowest ``best_key`` so far; a chunk that lowers it is passed to
    ``on_best``."""
    if record.get(scoring.best_key, float("inf")) < best:
        best = record[scoring.best_key]
        if scoring.on_best is not None:
            scoring.on_best(chunk, runner)
    return best


def _reaches(record: dict, target: float | None) -> bool:
    """Whether ``record``'s validation theta RMSE is at or below ``target``."""
    value = record.get(TARGET_KEY)
    return target is not None and value is not None and value <= target


def _postfix(record: dict, val_theta_rmse: float | None) -> dict:
    out = {
        "steps": f"{int(record['env_steps']):,}",
        "upd/s": f"{record['updates_per_s']:.0f}",
        "cost": f"{record['cost']:.2e}",
    }
    if val_theta_rmse is not None:
        out["val_theta_rmse"] = f"{val_theta_rmse:.2e}"
    return out
