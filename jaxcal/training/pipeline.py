"""The training job: data -> surrogate D -> policy -> test scores, in one run folder.

:func:`run_training` is what ``python -m jaxcal.train`` runs (paper §3 and Algorithm
1, with the set-up choices of ``design/calibration.md``):

1. the run folder ``<runs_dir>/<name>`` is checked, without writing: it must be
   writable, and a stored config must match for a resume
   (:func:`jaxcal.training.run_dir.check_run_dir`);
2. the data file is generated if it is missing and a generator preset is named
   (``python -m jaxcal.generate`` in a subprocess, so the engine's float64 setting
   does not leak into training), then the train / val / test units and the one
   :class:`~jaxcal.problem.Problem` are read (:func:`read_run_data`: an N-CMAPSS
   file through :mod:`jaxcal.training.data`, any model's rows through
   :mod:`jaxcal.training.tables`). Only then, every check of the config and the data
   passed, is the run folder created with its ``config.json``
   (:func:`jaxcal.training.run_dir.prepare_run_dir`): a start that fails leaves
   nothing behind that would block the corrected command;
3. the surrogate D is fitted on the training units' transitions or restored
   (:mod:`jaxcal.training.surrogate_stage`); ``dynamics=physics`` skips it; data
   without true theta fit it on units simulated from the model
   (:mod:`jaxcal.training.simulated`, which makes every labelled unit a run needs:
   the user's labels only score);
4. the policy learns on the training units' (w, x) only, no theta label
   (:mod:`jaxcal.training.policy_stage`); a model with memory trains on its own
   step (``dynamics=physics``), the environment carrying its state, and episodes
   start from the reference state track
   (:func:`jaxcal.envs.memory.reference_states`: the model run along each unit with
   the prior theta, label-free, what the deployed calibrator carries from a unit's
   first sample); validation units are scored every ``eval_every`` chunks (theta
   RMSE for progress only; the label-free tracking RMSE also selects the kept
   policy when ``budget.select=val_tracking``); with ``budget.target_theta_rmse``
   set, every scoring also runs the test units, for reporting only (the job's time
   to target; selection never sees a test score);
5. the kept policy runs once through every test unit's whole trajectory (the
   deployment calibrator of :mod:`jaxcal.calibrators.policy`, ``lax.scan`` vmapped
   over units) and ``final.json`` gets the test theta RMSE, the tracking RMSE, wall
   time, updates/s and env steps/s, the time to target (plus, for transparency, the
   scores of the last policy and of the last online actor);
6. the kept policy's run over simulated units (or the labelled validation units,
   ``simulate.band``) fits its split-conformal theta band, written to
   ``uncertainty.json``; ``final.json`` gets the band's 90 % coverage on the test
   units (:mod:`jaxcal.training.uncertainty_stage`) and what was simulated with
   which noise (``simulated``).

``simulate.train=simulated`` (the default preset on any model's data) trains the
policy on simulated copies of the training units, its cost on their noise-free
outputs; ``budget.select=sim_theta`` keeps the policy with the lowest theta RMSE on
simulated validation units.

The deployed actor is ``budget.policy``: by default the Polyak-averaged target policy
of Algorithm 1 (LAC, CLAC; SAC has none and deploys its online actor). Besides the
runner checkpoints, every checkpoint step saves the deployable
:class:`~jaxcal.calibrators.policy.PolicyParams` (actor, dynamics parameters,
normalisation, action box) under ``policy/``, and the selected one under
``policy_best/``; :func:`jaxcal.training.runs.load_run` loads a run from those and
``config.json`` / ``data.json`` (the model spec and ``Problem.to_json()``) alone.

No x64 switch here: a model that needs float64 (``model.x64``) with
``dynamics=physics`` is an error unless the caller enabled x64 (the command line
does).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.policy import (
    PolicyParams,
    policy_params_from_env,
    range_check,
)
from jaxcal.checkpoint import Checkpointer
from jaxcal.config import TrainConfig
from jaxcal.envs.env_data import compute_norm_stats
from jaxcal.envs.increment import increment_step_ref
from jaxcal.envs.memory import as_stateful, reference_states
from jaxcal.envs.tracking import EnvParams, make_env_params
from jaxcal.problem import Normalisation, Problem
from jaxcal.training.components import (
    check_dynamics,
    env_config,
    make_components,
    make_dynamics,
)
from jaxcal.training.data import CalibrationData, UnitArrays
from jaxcal.training.model_source import (
    check_source_unchanged,
    model_source,
    store_model_source,
)
from jaxcal.training.policy_stage import train_policy
from jaxcal.training.run_data import (  # noqa: F401 (re-exported)
    GenerationError,
    ensure_data_file,
    model_spec,
    read_run_data,
)
from jaxcal.training.run_dir import (
    DATA_FILE,
    FINAL_FILE,
    POLICY_BEST_DIR,
    POLICY_DIR,
    check_run_dir,
    prepare_run_dir,
    write_json,
)
from jaxcal.training.run_guard import hold_run, run_folder
from jaxcal.training.scoring import describe_units, score_units, theta_rmse
from jaxcal.training.simulated import Simulations, parse_noise
from jaxcal.training.surrogate_stage import fit_or_restore_surrogate
from jaxcal.training.uncertainty_stage import (
    fit_policy_band,
    scored_mask,
    time_to_target,
)


def _env_params(
    units: UnitArrays,
    problem: Problem,
    dyn_params,
    dtype,
    dynamics_kind: str,
    max_increment: float | None = None,
    x_target: np.ndarray | None = None,
    stats_of: UnitArrays | None = None,
) -> EnvParams:
    # The normalisation is computed here, in the run's dtype, as it always was: a
    # float32 run keeps bit for bit the statistics (and so the training) it had.
    # Simulated units are normalised with the real training units' statistics
    # (``stats_of``), what the deployed policy sees.
    w, x = units.w.astype(dtype), units.x.astype(dtype)
    stats = None
    if stats_of is not None:
        stats = compute_norm_stats(
            stats_of.w.astype(dtype), stats_of.x.astype(dtype), stats_of.lengths
        )
    z_ref = None  # a static model: Z = 0
    dyn = as_stateful(make_dynamics(dynamics_kind, problem))
    if problem.model.is_stateful:
        # The label-free reference: the model along each unit at the prior theta
        # (the joint UKF's filtered states would be closer; see the module note).
        z_ref = reference_states(
            dyn, dyn_params, w, x, units.lengths, problem.theta_prior
        )
    params = make_env_params(
        w,
        x,
        units.lengths,
        problem.theta_low.astype(dtype),
        problem.theta_high.astype(dtype),
        dyn_params,
        stats=stats,
        z_ref=z_ref,
        x_target=None if x_target is None else x_target.astype(dtype),
    )
    if max_increment is None:
        return params
    return params.replace(
        step_ref=jnp.asarray(
            increment_step_ref(dyn, params, problem.theta_prior, max_increment), dtype
        )
    )


def _throughput(records: list[dict]) -> dict:
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


def run_training(
    cfg: TrainConfig,
    *,
    log: Callable[[str], None] = print,
    clock: Callable[[], float] | None = None,
    finish: Callable[[dict], dict] | None = None,
) -> dict:
    """Runs (or resumes) the training job of ``cfg``; returns the ``final.json`` dict.

    Every check of the config and the data runs before the run folder is created or
    written, so a failed start leaves nothing behind.

    ``clock()`` gives the seconds since the job's start (earlier sessions included;
    the command line starts it before its imports), which time to target reads;
    ``None``: from this call's start. ``finish(final)`` completes the ``final.json``
    dict before its one write (the command line adds its wall times), still under
    the run's lock.

    The run folder is locked (:func:`jaxcal.training.run_guard.hold_run`) from its
    first write to its last: a second training of the name fails at once. It keeps a
    copy of a model file (:mod:`jaxcal.training.model_source`), which a resume
    checks is unchanged.

    Raises:
        ValueError: bad data selection, an unwritable run folder or one made by
            another config, a model no run could load again, or a model file
            changed since the run started.
        RunInUseError: another training holds the run (a ``ValueError``).
    """
    wall_start = time.perf_counter()
    if clock is None:
        clock = lambda: time.perf_counter() - wall_start  # noqa: E731
    run_dir = run_folder(cfg.output.runs_dir, cfg.run_name)
    status = check_run_dir(run_dir, cfg)  # writes nothing; fails if in use
    state = {
        "new": "new",
        "resume": "resuming",
        "stale": "new; its folder held only the config.json of a failed start, "
        "which is replaced",
    }[status]
    log(f"run {run_dir} ({state}), seed {cfg.seed}")
    path = ensure_data_file(cfg, log)
    data = read_run_data(cfg, path=path, log=log)
    problem = data.problem
    model = problem.model
    check_dynamics(cfg.dynamics, model)  # a model with memory: physics only
    parse_noise(cfg.noise, problem.output_names)  # checked before any write
    # float64 only around a model that needs it; everything else in float32
    dtype = np.float64 if cfg.dynamics == "physics" and model.x64 else np.float32
    log(
        f"model {model.name!r}; data {path}: theta {list(data.theta_names)} in "
        f"[{', '.join(f'{v:.4g}' for v in data.theta_low)}] .. "
        f"[{', '.join(f'{v:.4g}' for v in data.theta_high)}]; {len(data.sensors)} "
        f"sensors; units train {describe_units(data.info['units']['train'])}, val "
        f"{describe_units(data.info['units']['val'])}, test "
        f"{describe_units(data.info['units']['test'])}"
    )
    source = model_source(model_spec(cfg, model))  # a model a run can load again
    with hold_run(run_dir):  # one training of the name at a time, to its last write
        check_source_unchanged(run_dir, source)  # a resume: the model it started on
        prepare_run_dir(run_dir, cfg)  # the first write: every check above has passed
        stored = store_model_source(run_dir, source)
        final = _train(cfg, run_dir, data, path, dtype, stored, log, clock, wall_start)
        if finish is not None:
            final = finish(final)
        write_json(run_dir / FINAL_FILE, final)
    return final


def _train(
    cfg: TrainConfig,
    run_dir: Path,
    data: CalibrationData,
    path: Path,
    dtype,
    model_record: dict,
    log: Callable[[str], None],
    clock: Callable[[], float],
    wall_start: float,
) -> dict:
    """The job of :func:`run_training` once its checks passed and it holds the run:
    surrogate, policy, test scores, band; returns the ``final.json`` dict."""
    problem = data.problem
    model = problem.model
    key_surrogate, key_runner = jax.random.split(jax.random.key(cfg.seed))
    sims = Simulations(cfg, data, log)
    surrogate_report = None
    dyn_params = None
    if cfg.dynamics == "surrogate":
        dyn_params, surrogate_report = fit_or_restore_surrogate(
            key_surrogate,
            data if data.train.theta is not None else sims.labelled_train(),
            cfg.surrogate,
            run_dir,
            progress=cfg.output.progress,
            log=log,
        )
    incremental = cfg.env.action == "increment"
    fleet, target = sims.training_fleet()
    train_params = _env_params(
        fleet, problem, dyn_params, dtype, cfg.dynamics,
        cfg.env.max_increment if incremental else None,
        x_target=target, stats_of=None if fleet is data.train else data.train,
    )  # fmt: skip
    if incremental:
        log(
            "incremental actions: step gate n_ref "
            f"{np.asarray(train_params.step_ref).tolist()} (residual RMS), largest "
            f"step {cfg.env.max_increment:g} of the box width"
        )
    norm = (train_params.w_mean, train_params.w_std, train_params.x_mean,
            train_params.x_std)  # fmt: skip
    problem = dataclasses.replace(
        problem, norm=Normalisation(*(np.asarray(a, np.float64) for a in norm))
    )
    write_json(
        run_dir / DATA_FILE,
        {"model_spec": model_spec(cfg, model), "model_source": model_record,
         "x64": model.x64,
         "problem": problem.to_json(), **data.info,
         # kept at the top for readers of the older layout (the paper suite)
         "sensors": problem.output_names, "theta_names": problem.theta_names},
    )  # fmt: skip
    start = problem.theta_prior if cfg.env.start == "prior" else None
    env_cfg = env_config(
        sims.with_noise_floor(cfg),
        len(model.conditions),
        len(problem.output_names),
        len(problem.theta_names),
    )
    parts = make_components(cfg.dynamics, problem, env_cfg, cfg.agent, cfg.runner)
    check = range_check(problem)  # samples far outside the training range: flagged

    def run(units: UnitArrays, params: PolicyParams):
        return parts.run_units(
            params, units.w.astype(dtype), units.x.astype(dtype), units.mask, check
        )

    def score(units: UnitArrays, params: PolicyParams, out=None) -> dict:
        out = run(units, params) if out is None else out
        return score_units(
            out.theta,
            out.xhat,
            units.theta,
            units.x,
            units.mask,
            problem.norm.x_std,
            problem.output_names,
            problem.theta_names,
            reason=out.reason,
        )

    def deployable(agent_state, which: str = cfg.budget.policy) -> PolicyParams:
        actor = agent_state.actor.params
        if which == "target":
            actor = getattr(agent_state, "target_actor_params", actor)
        return policy_params_from_env(
            train_params, actor, max_increment=env_cfg.max_increment,
            theta_start=start,
        )  # fmt: skip

    select_units = sims.selection_units() if cfg.budget.select == "sim_theta" else None

    def val_scorer(agent_state) -> dict:
        params = deployable(agent_state)
        scores = {}
        if data.val is not None:
            scores = score(data.val, params)
            keys = ("theta_rmse", "tracking_rmse_norm")
            scores = {k: scores[k] for k in keys if scores[k] is not None}
        if select_units is not None:
            out = run(select_units, params)
            width = problem.theta_high - problem.theta_low
            scores["sim_theta_rmse"], _ = theta_rmse(
                out.theta / width,
                select_units.theta / width,
                scored_mask(select_units, out),
            )
        return scores

    def test_reporter(agent_state) -> dict:
        # Reporting only (time to target): train_policy logs it as test_*, and
        # selection reads val_* alone, so test labels never choose the policy.
        out = run(data.test, deployable(agent_state))
        pooled, _ = theta_rmse(out.theta, data.test.theta, scored_mask(data.test, out))
        return {"theta_rmse": pooled}

    target = cfg.budget.target_theta_rmse
    if target is not None and data.test.theta is None:
        log("budget.target_theta_rmse: the test units have no true theta, so the "
            "time to target is not measured")  # fmt: skip
        target = None
    select = (cfg.budget.select == "val_tracking" and data.val is not None) or (
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

        def save_latest(step: int, runner) -> None:
            params = deployable(runner.agent_state)
            latest_ckpt.save(step, jax.device_get(params), wait=True)

        def save_best(step: int, runner) -> None:
            # A chunk re-run after a resume reproduces the policy already saved.
            if step not in best_ckpt.all_steps():
                params = deployable(runner.agent_state)
                best_ckpt.save(step, jax.device_get(params), wait=True)

        policy = train_policy(
            key_runner,
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
            scorer=val_scorer
            if data.val is not None or select_units is not None
            else None,
            best_key="val_sim_theta_rmse"
            if cfg.budget.select == "sim_theta"
            else "val_tracking_rmse_norm",
            on_checkpoint=save_latest,
            on_best=save_best if select else None,
            reporter=test_reporter if target is not None else None,
            target=target,
            clock=clock,
            progress=cfg.output.progress,
            log=log,
        )
        last = deployable(policy.runner.agent_state)
        selected, selected_step = last, policy.chunks_done
        if select and best_ckpt.latest_step() is not None:
            selected_step = best_ckpt.latest_step()
            selected = best_ckpt.restore(selected_step, last)
    test_out = run(data.test, selected)
    test = score(data.test, selected, test_out)
    records = policy.records
    val_record = next((r for r in records if r["step"] == selected_step), {})
    final = {
        "run": str(run_dir),
        "agent": cfg.agent_name,
        "dynamics": cfg.dynamics,
        "preset": cfg.preset,
        "seed": cfg.seed,
        "data": str(path),
        "model": model.name,
        "theta_names": list(data.theta_names),
        "test_units": data.info["units"]["test"],
        "select": cfg.budget.select if select else "last",
        "policy": cfg.budget.policy
        if hasattr(policy.runner.agent_state, "target_actor_params")
        else "online",
        "selected_chunk": selected_step,
        "test": test,
        "test_last": test
        if selected_step == policy.chunks_done
        else score(data.test, last),
        "test_online_last": score(
            data.test, deployable(policy.runner.agent_state, "online")
        ),
        "val_selected": {
            k[4:]: v for k, v in val_record.items() if k.startswith("val_")
        },
        "chunks": policy.chunks_done,
        "stopped_early": policy.stopped_early,
        "env_steps": int(policy.runner.env_steps),
        "num_updates": int(policy.runner.num_updates),
        "train_seconds": float(sum(r["chunk_seconds"] for r in records)),
        **_throughput(records),
        "session_wall_seconds": time.perf_counter() - wall_start,
        "surrogate": surrogate_report,
        **time_to_target(records, target),
    }
    band_units, fitted_on = sims.band_units()
    band_out = None if band_units is None else run(band_units, selected)
    names = tuple(data.theta_names)
    final.update(
        fit_policy_band(
            band_units, band_out, data.test, test_out, run_dir, names,
            fitted_on=fitted_on, log=log,
        )
    )  # fmt: skip
    final["simulated"] = sims.report()
    return final
