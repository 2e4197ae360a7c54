"""A trained run folder, loaded: its problem, policy and dynamics, ready to deploy.

A run folder written by :func:`jaxcal.training.pipeline.run_training` holds
everything a policy needs: ``config.json`` (architecture, dynamics), ``data.json``
(the model spec and ``Problem.to_json()``: names, units, action box, normalisation,
training input range) and ``policy/`` (actor weights, surrogate weights,
normalisation and action box, saved at every checkpoint) and ``model/`` (the copy of
a model file). No data file and no training code path is needed. :func:`load_run`
rebuilds the run's own model (:mod:`jaxcal.training.model_source`), never importing
a path outside the folder; ``data.json`` files of the older layout (the turbofan's
``RunMeta`` fields) are read too.

This module sits below the command lines: :mod:`jaxcal.deploy` re-exports it for
users, and :func:`jaxcal.calibrate` (``method="policy"``) and the fleet runners use
it directly.

Float64: a run whose model needs it (``model.x64``) with ``dynamics=physics`` is
refused with a clear message unless x64 is enabled; the command lines enable it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.agents.networks import make_networks
from jaxcal.calibrators.gated import feedback_sensitivity, make_gated_calibrator
from jaxcal.calibrators.interface import Calibrator, SampleCheck
from jaxcal.calibrators.policy import (
    IncrementPolicyParams,
    PolicyParams,
    StartedIncrementPolicyParams,
    make_policy_calibrator,
    range_check,
)
from jaxcal.calibrators.uncertainty import ThetaBand, load_band
from jaxcal.checkpoint import Checkpointer, load_config
from jaxcal.config import TrainConfig
from jaxcal.envs.memory import StatefulDynamics
from jaxcal.envs.tracking import Dynamics
from jaxcal.problem import Problem
from jaxcal.surrogate.model import init_surrogate_params
from jaxcal.training.components import env_config, make_agent, make_dynamics
from jaxcal.training.model_check import check_run_model  # noqa: F401 (re-exported)
from jaxcal.training.model_source import (  # noqa: F401 (re-exported)
    adopt_model_file,
    load_run_model,
    recorded_source,
)
from jaxcal.training.run_dir import DATA_FILE, POLICY_BEST_DIR, POLICY_DIR, read_json

# Runs of the older data.json layout are the turbofan's, which needs float64.
_LEGACY_X64 = True


class LoadedRun(NamedTuple):
    """A trained policy ready to run.

    Attributes:
        run_dir: the run folder.
        config: its resolved :class:`~jaxcal.config.TrainConfig`.
        problem: the run's :class:`~jaxcal.problem.Problem` (model, names, box,
            normalisation, training input range).
        params: the deployable :class:`PolicyParams`.
        actor: the actor module (static).
        dynamics: the transition x-hat_t = D(w_t, x-hat_{t-1}, theta_t) (static), a
            :class:`~jaxcal.envs.memory.StatefulDynamics` for a model with memory.
        step: the checkpoint step (chunks trained) the policy comes from.
        band: the calibrated error band of the kept policy (``uncertainty.json``,
            fitted on the validation units at the end of training); ``None`` for a
            run without one.
        model_source: what the run stores of its model (``data.json``
            ``"model_source"``, :mod:`jaxcal.training.model_source`); ``None`` for a
            run of the older layout (its registered model's name, if it had one).
    """

    run_dir: Path
    config: TrainConfig
    problem: Problem
    params: PolicyParams
    actor: nn.Module
    dynamics: Dynamics | StatefulDynamics
    step: int
    band: ThetaBand | None = None
    model_source: dict | None = None

    @property
    def meta(self) -> Problem:
        """The problem, under the name older callers use (``range_check(run.meta)``)."""
        return self.problem


def needs_x64(run_dir: str | os.PathLike) -> bool:
    """Whether loading the run needs x64 (``dynamics=physics`` on a float64 model),
    read from its files without loading the model."""
    cfg = load_config(run_dir)
    if cfg.get("dynamics") != "physics":
        return False
    data = read_json(Path(run_dir) / DATA_FILE)
    return bool(data.get("x64", _LEGACY_X64))


def run_problem(data: dict, model=None, run_dir: str | os.PathLike = ".") -> Problem:
    """The :class:`Problem` of a ``data.json`` dict (either layout).

    Args:
        data: the parsed ``data.json``.
        model: the model (``None``: the run's own,
            :func:`~jaxcal.training.model_source.load_run_model`).
        run_dir: the run folder ``data`` comes from (where its model copy lies).
    """
    model = model or load_run_model(run_dir, data)
    if "problem" in data:
        return Problem.from_json(data["problem"], model)
    # the older layout: RunMeta fields + the box and normalisation beside them,
    # mapped onto the current one
    ranges = ("w_low", "w_high", "x_low", "x_high")
    x_std = np.asarray(data["norm"]["x_std"], np.float64)
    current = {
        **{
            k: data[k] for k in ("theta_names", "theta_base", "theta_low", "theta_high")
        },
        "output_names": data["sensors"],
        "norm": data["norm"],
        "noise_std": 0.01 * x_std,
        "noise_source": "provisional (1 % of each output's spread)",
        "input_range": {k: data[k] for k in ranges}
        if data.get("w_low") is not None
        else None,
    }
    return Problem.from_json(current, model)


def load_run(
    run_dir: str | os.PathLike, *, which: str = "selected", step: int | None = None
) -> LoadedRun:
    """Load a run's policy.

    Args:
        run_dir: the run folder.
        which: ``"selected"``: the policy the run kept (``budget.select``: the best
            validation tracking RMSE, or the last one); ``"last"``: the latest
            checkpoint.
        step: a specific checkpoint step of ``which`` (``None``: the newest).

    The model is the run's own (:mod:`jaxcal.training.model_source`: the copy of a
    model file kept in the folder, or a registered or installed module's by name),
    never a path outside the folder. Loading a run runs its model's code: load only
    run folders you trust.

    Raises:
        FileNotFoundError: the folder is not a run, or it has no policy checkpoint.
        ValueError: the checkpoint does not match the run's config, the model
            cannot be loaded (its copy edited, or a file outside the folder), or it
            needs x64 and x64 is off.
    """
    if which not in ("selected", "last"):
        raise ValueError(f"which must be 'selected' or 'last', got {which!r}")
    run_dir = Path(run_dir)
    cfg = load_config(run_dir, TrainConfig)
    if needs_x64(run_dir) and not jax.config.jax_enable_x64:
        raise ValueError(
            f"run {run_dir} uses dynamics=physics on a model that needs float64: "
            "call jax.config.update('jax_enable_x64', True) (or "
            "jaxcal.precision.enable_x64()) before loading it"
        )
    data = read_json(run_dir / DATA_FILE)
    problem = run_problem(data, run_dir=run_dir)  # its own model: never a path outside
    physics64 = cfg.dynamics == "physics" and problem.model.x64
    dtype = jnp.float64 if physics64 else jnp.float32
    dims = (
        len(problem.model.conditions), len(problem.output_names),
        len(problem.theta_names),
    )  # fmt: skip
    env_cfg = env_config(cfg, *dims)
    agent = make_agent(cfg.agent, env_cfg.observation_size, dims[2])

    def abstract(key):
        dyn = (
            init_surrogate_params(key, *dims, cfg.surrogate)
            if cfg.dynamics == "surrogate"
            else None
        )
        fields = dict(
            actor=agent.init(key).actor.params,
            dyn_params=dyn,
            w_mean=jnp.zeros(dims[0], dtype),
            w_std=jnp.ones(dims[0], dtype),
            x_mean=jnp.zeros(dims[1], dtype),
            x_std=jnp.ones(dims[1], dtype),
            theta_low=jnp.zeros(dims[2], dtype),
            theta_high=jnp.ones(dims[2], dtype),
        )
        if not env_cfg.incremental:
            return PolicyParams(**fields)
        fields.update(
            step_ref=jnp.ones(dims[2], dtype), max_increment=env_cfg.max_increment
        )
        if getattr(cfg.env, "start", "centre") == "prior":
            start = jnp.zeros(dims[2], dtype)
            return StartedIncrementPolicyParams(**fields, theta_start=start)
        return IncrementPolicyParams(**fields)

    target = jax.eval_shape(abstract, jax.random.key(0))
    folder = run_dir / POLICY_DIR
    best = run_dir / POLICY_BEST_DIR
    if which == "selected" and cfg.budget.select != "last" and best.is_dir():
        folder = best
    with Checkpointer(folder) as ckpt:
        if ckpt.latest_step() is None:
            raise FileNotFoundError(
                f"{folder} holds no policy checkpoint; train the run "
                "first (python -m jaxcal.train ...)"
            )
        step_given = step
        step = ckpt.latest_step() if step is None else step
        params = ckpt.restore(step, target)
    return LoadedRun(
        run_dir=run_dir,
        config=cfg,
        problem=problem,
        params=params,
        actor=make_networks(cfg.agent, dims[2]).actor,
        dynamics=make_dynamics(cfg.dynamics, problem),
        step=int(step),
        # the band belongs to the kept policy: none for another checkpoint
        band=load_band(run_dir) if which == "selected" and step_given is None else None,
        model_source=recorded_source(data),
    )


def run_check(run: LoadedRun) -> SampleCheck | None:
    """The run's valid input box (training range + margin; ``None``: finiteness).

    Pass it as ``check=`` to ``run_calibrator`` / ``run_fleet`` / the fleet paths.
    """
    return range_check(run.problem)


def load_calibrator(
    run_dir: str | os.PathLike | LoadedRun,
    anchor: str | os.PathLike | LoadedRun | None = None,
    *,
    warm_start: bool = False,
) -> Calibrator:
    """The run's policy as a ``Calibrator(init, step)`` (pure functions, not jitted).

    Use it like any other method: ``jax.jit(run_fleet, static_argnums=0)(cal, w, x,
    m)``, with ``check=run_check(run)`` to flag samples outside the training range.

    Args:
        run_dir: the run (folder or loaded).
        anchor: an absolute policy's run with its band (``uncertainty.json``): the
            run, an incremental policy, is then gated by it where the model misfits
            the data (:mod:`jaxcal.calibrators.gated`).
        warm_start: for one stream, one sample per call: the model's solver is
            warm-started from the previous sample when it can be
            (:func:`~jaxcal.calibrators.policy.make_policy_calibrator`); keep the
            default for ``run_fleet`` over many units.

    Raises:
        ValueError: the anchor has no band, its names differ from the run's, or the
            run is not an incremental policy.
    """
    run = as_loaded(run_dir)
    cal = make_policy_calibrator(
        run.actor, run.dynamics, run.params, run.band, warm_start=warm_start
    )
    if anchor is None:
        return cal
    anchor = as_loaded(anchor)
    check_anchor(run, anchor)
    anchor_cal = make_policy_calibrator(
        anchor.actor, anchor.dynamics, anchor.params, anchor.band,
        warm_start=warm_start,
    )  # fmt: skip
    return make_gated_calibrator(
        cal,
        anchor_cal,
        x_std=run.params.x_std,
        sensitivity=feedback_sensitivity(run.params),
        anchor_band=anchor.band,
    )


def as_loaded(run: str | os.PathLike | LoadedRun) -> LoadedRun:
    """``run`` loaded (a :class:`LoadedRun` passes through)."""
    return run if isinstance(run, LoadedRun) else load_run(run)


def check_anchor(run: LoadedRun, anchor: LoadedRun) -> None:
    """An anchor must calibrate the same problem and carry its band.

    Raises:
        ValueError: naming the anchor's folder and what differs.
    """
    if anchor.band is None:
        raise ValueError(
            f"anchor run {anchor.run_dir} has no uncertainty.json (the error band "
            "the training job fits at its end): the gate's threshold is the "
            "anchor's 90 % half-width"
        )
    for field in ("theta_names", "output_names"):
        if tuple(getattr(anchor.problem, field)) != tuple(getattr(run.problem, field)):
            raise ValueError(
                f"anchor run {anchor.run_dir} has {field} "
                f"{list(getattr(anchor.problem, field))}, the run {run.run_dir} "
                f"{list(getattr(run.problem, field))}: both must calibrate one problem"
            )
