"""The training job: data -> surrogate D -> policy -> test scores, in one run folder.

:func:`run_training` is what ``python -m jaxcal.train`` runs (paper §3 and Algorithm
1, with the set-up choices of ``design/calibration.md``):

1. the run folder ``<runs_dir>/<name>`` is checked without writing: writable, and a
   stored config must match for a resume (:func:`jaxcal.runs.folder.check_run_dir`);
2. the data file is generated if it is missing and a generator preset is named
   (:data:`jaxcal.models.TRAINING_FILES`; its float64 scope does not leak into
   training), then the train / val / test units and the one
   :class:`~jaxcal.problem.Problem` are read (:func:`read_run_data`), with the run's
   one normalisation, computed there in the run's dtype (:func:`run_dtype`) and
   carried unchanged to the environment, the deployed policy and ``data.json``. Only
   then, every check passed, is the run folder created with its ``config.json``
   (:func:`jaxcal.runs.folder.prepare_run_dir`): a failed start leaves nothing that
   would block the corrected command;
3. the surrogate D is fitted or restored (:mod:`jaxcal.training.stages.surrogate`;
   ``dynamics=physics`` skips it); data without true theta fit it on units simulated
   from the model (:mod:`jaxcal.training.data.simulated`, which makes every labelled
   unit a run needs: the user's labels only score);
4. the policy learns on the training units' (w, x) only, no theta label
   (:mod:`jaxcal.training.data.train_env`, :mod:`jaxcal.training.stages.policy`,
   :mod:`jaxcal.training.kept_policy`, :mod:`jaxcal.training.scoring.policy`); a
   model with memory trains on its own step, episodes starting from the label-free
   reference state track (:func:`jaxcal.envs.memory.reference_states`); validation
   units are scored every ``eval_every`` chunks (theta RMSE for progress and the
   time to target only; the label-free tracking RMSE selects the kept policy under
   ``budget.select=val_tracking``, simulated units' theta RMSE under ``sim_theta``);
5. the kept policy runs once through every test unit's whole trajectory (the
   deployment calibrator, :mod:`jaxcal.calibrators.methods.policy.calibrator`) and
   ``final.json`` gets its scores, wall time and throughput
   (:mod:`jaxcal.training.scoring.final_report`);
6. the kept policy's run over simulated units (or the labelled validation units,
   ``simulate.band``) fits its split-conformal theta band (``uncertainty.json``;
   :mod:`jaxcal.training.stages.uncertainty`), whose 90 % coverage on the test units
   goes to ``final.json`` with what was simulated (``simulated``).

The deployed actor is ``budget.policy``: by default the Polyak-averaged target policy
of Algorithm 1 (LAC, CLAC; SAC has none and deploys its online actor). Every
checkpoint step also saves the deployable
:class:`~jaxcal.calibrators.methods.policy.calibrator.PolicyParams` under ``policy/``
and the selected one under ``policy_best/``; :func:`jaxcal.deploy.load_run` loads a
run from those and ``config.json`` / ``data.json`` alone.

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

from jaxcal.problem import Problem
from jaxcal.runs.folder import (
    DATA_FILE,
    FINAL_FILE,
    check_run_dir,
    prepare_run_dir,
    write_json,
)
from jaxcal.runs.lock import hold_run, run_folder
from jaxcal.training.components import (
    agent_config,
    check_dynamics,
    env_config,
    make_components,
)
from jaxcal.training.config import TrainConfig
from jaxcal.training.data.calibration import CalibrationData
from jaxcal.training.data.run import (  # noqa: F401 (re-exported)
    GenerationError,
    ensure_data_file,
    model_spec,
    read_run_data,
    run_dtype,
)
from jaxcal.training.data.simulated import Simulations, parse_noise
from jaxcal.training.data.train_env import make_training_env
from jaxcal.training.kept_policy import train_kept_policy
from jaxcal.training.model_source import (
    check_source_unchanged,
    model_source,
    store_model_source,
)
from jaxcal.training.scoring.final_report import final_report, with_tuning
from jaxcal.training.scoring.policy import make_policy_scoring
from jaxcal.training.scoring.trajectories import describe_units
from jaxcal.training.stages.surrogate import fit_or_restore_surrogate
from jaxcal.training.stages.tune import tune_kept
from jaxcal.training.stages.uncertainty import band_runs, fit_policy_band


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

    The run folder is locked (:func:`jaxcal.runs.lock.hold_run`) from its
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
    dtype = run_dtype(cfg, model)  # the dtype data.problem.norm was computed in
    units = {k: describe_units(v) for k, v in data.info["units"].items()}
    log(
        f"model {model.name!r}; data {path}: theta {list(problem.theta_names)} in "
        f"[{', '.join(f'{v:.4g}' for v in problem.theta_low)}] .. "
        f"[{', '.join(f'{v:.4g}' for v in problem.theta_high)}]; "
        f"{len(problem.output_names)} sensors; units train {units['train']}, val "
        f"{units['val']}, test {units['test']}"
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


def fit_episode(cfg: TrainConfig, longest: int, log: Callable[[str], None]):
    """``cfg`` with its training windows fitted to the data: a window of
    ``env.episode_length`` steps needs that many rows plus two, and where no unit
    has them every episode would start on the first unit (the draw among no
    eligible unit) and run past its end. Shorter windows then, said in the log."""
    if cfg.env.episode_length + 2 <= longest:
        return cfg
    if longest < 3:
        raise ValueError(
            f"the longest training unit has {longest} rows: a training window "
            "needs at least 3"
        )
    log(
        f"env.episode_length {cfg.env.episode_length} needs units of "
        f"{cfg.env.episode_length + 2} rows, the longest training unit has "
        f"{longest}: training windows of {longest - 2} steps"
    )
    env = dataclasses.replace(cfg.env, episode_length=longest - 2)
    return dataclasses.replace(cfg, env=env)


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
    problem = data.problem  # its normalisation the run's one, never replaced
    model = problem.model
    key_surrogate, key_runner = jax.random.split(jax.random.key(cfg.seed))
    sims = Simulations(cfg, data, log)
    dyn_params, surrogate_report = _fit_dynamics(
        cfg, key_surrogate, data, sims, run_dir, log
    )
    train_params = make_training_env(cfg, data, sims, dyn_params, dtype, log)
    cfg = fit_episode(cfg, int(jax.device_get(train_params.lengths).max()), log)
    write_json(run_dir / DATA_FILE, _data_record(cfg, problem, data, model_record))
    env_cfg = env_config(
        sims.with_noise_floor(cfg),
        len(model.conditions),
        len(problem.output_names),
        len(problem.theta_names),
    )
    parts = make_components(
        cfg.dynamics, problem, env_cfg, agent_config(cfg, env_cfg), cfg.runner
    )
    select_units = sims.selection_units() if cfg.budget.select == "sim_theta" else None
    scoring = make_policy_scoring(
        cfg, data, problem, parts, train_params, env_cfg.max_increment, dtype,
        select_units,
    )  # fmt: skip
    target = _val_target(cfg, data, log)
    kept = train_kept_policy(
        cfg, key_runner, run_dir, parts, train_params, scoring,
        has_val=data.val is not None, target=target, clock=clock,
        wall_start=wall_start, log=log,
    )  # fmt: skip
    kept, tuned = tune_kept(cfg, kept, parts, sims, scoring, run_dir, log)
    test_out = scoring.run(data.test, kept.selected)
    test = scoring.score(data.test, kept.selected, test_out)
    final = final_report(
        cfg, run_dir, path, data, kept, test, surrogate_report, target,
        wall_start,
    )  # fmt: skip
    band_units, fitted_on = sims.band_units()
    made = kept.val_out if band_units is data.val else None
    band_out, scales = band_runs(
        scoring.run, band_units, data.test, kept.selected, made
    )
    names = tuple(data.problem.theta_names)
    final.update(
        fit_policy_band(
            band_units, band_out, data.test, test_out, run_dir, names,
            fitted_on=fitted_on, scales=scales, log=log,
        )
    )  # fmt: skip
    final["tune"] = tuned
    final["training_gain"] = with_tuning(final.get("training_gain"), tuned)
    final["simulated"] = sims.report()
    return final


def _fit_dynamics(
    cfg: TrainConfig, key, data: CalibrationData, sims, run_dir: Path, log
):
    """``(dyn_params, surrogate report)``: the surrogate D fitted or restored
    (:mod:`jaxcal.training.stages.surrogate`; on simulated labelled units when the
    data carry no true theta), or ``(None, None)`` with ``dynamics=physics``."""
    if cfg.dynamics != "surrogate":
        return None, None
    return fit_or_restore_surrogate(
        key,
        data if data.train.theta is not None else sims.labelled_train(),
        cfg.surrogate,
        run_dir,
        progress=cfg.output.progress,
        log=log,
    )


def _data_record(
    cfg: TrainConfig, problem: Problem, data: CalibrationData, model_record: dict
) -> dict:
    """The run's ``data.json``: the model (its spec, the kept source, float64), the
    problem with the training normalisation, and the data's provenance."""
    model = problem.model
    return {
        "model_spec": model_spec(cfg, model), "model_source": model_record,
        "x64": model.x64,
        "problem": problem.to_json(), **data.info,
        # kept at the top for readers of the older layout (the paper suite)
        "sensors": problem.output_names, "theta_names": problem.theta_names,
    }  # fmt: skip


def _val_target(
    cfg: TrainConfig, data: CalibrationData, log: Callable[[str], None]
) -> float | None:
    """``budget.target_theta_rmse``, or ``None`` when no validation unit has a true
    theta to measure the time to target by (said in the log)."""
    target = cfg.budget.target_theta_rmse
    if target is not None and (data.val is None or data.val.theta is None):
        log("budget.target_theta_rmse: the validation units have no true theta, so "
            "the time to target is not measured")  # fmt: skip
        target = None
    return target
