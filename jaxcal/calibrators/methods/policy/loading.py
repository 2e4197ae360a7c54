"""Reading a trained run folder: its problem, policy and dynamics, ready to deploy.

A run folder written by :func:`jaxcal.training.pipeline.run_training` holds
everything a policy needs: ``config.json`` (architecture, dynamics), ``data.json``
(the model spec and ``Problem.to_json()``: names, units, action box, normalisation,
training input range) and ``policy/`` (actor weights, surrogate weights,
normalisation and action box, saved at every checkpoint) and ``model/`` (the copy of
a model file). No data file and no training code path is needed. :func:`load_run`
rebuilds the run's own model (:mod:`jaxcal.training.model_source`), never importing
a path outside the folder, and running the folder's model copy only with the user's
consent (``trust_code=True``, or the same file named by the user in this process:
:mod:`jaxcal.trust`, ``docs/trust.md``); ``data.json`` files of the older layout (the
turbofan's ``RunMeta`` fields) are read too.

The policy method reads a run here, with the training job's config, components and
model source, which import nothing above the calibrators (``tests/test_architecture.py``
places them at this layer); :mod:`jaxcal.deploy` re-exports :func:`load_run`.

Float64: a run whose model needs it (``model.x64``) with ``dynamics=physics`` is
refused with a clear message unless x64 is enabled; the command lines enable it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.agents.networks import make_networks
from jaxcal.calibrators.methods.policy.calibrator import (
    IncrementPolicyParams,
    PolicyParams,
    StartedIncrementPolicyParams,
    filter_settings,
    with_output_states,
)
from jaxcal.calibrators.uncertainty.conformal import load_band
from jaxcal.precision import require_x64
from jaxcal.problem import Problem, provisional_noise
from jaxcal.runs.checkpoint import Checkpointer, load_config
from jaxcal.runs.folder import (
    DATA_FILE,
    POLICY_BEST_DIR,
    POLICY_DIR,
    POLICY_TUNED_DIR,
    read_json,
)
from jaxcal.surrogate.model import init_surrogate_params
from jaxcal.training.components import (
    agent_config,
    env_config,
    make_agent,
    make_dynamics,
)
from jaxcal.training.config import TrainConfig
from jaxcal.training.model_source import load_run_model, recorded_source

# Runs of the older data.json layout are the turbofan's, which needs float64.
_LEGACY_X64 = True


class LoadedRun(NamedTuple):
    """A trained policy ready to run (:func:`jaxcal.deploy.load_run`).

    Attributes:
        run_dir: the run folder.
        config: its resolved :class:`~jaxcal.training.config.TrainConfig`.
        problem: the run's :class:`~jaxcal.problem.Problem` (model, names, box,
            normalisation, training input range).
        params: the deployable
            :class:`~jaxcal.calibrators.methods.policy.calibrator.PolicyParams` (or its
            incremental variants).
        actor: the actor module (static).
        dynamics: the transition x-hat_t = D(w_t, x-hat_{t-1}, theta_t) (static), a
            :class:`~jaxcal.envs.memory.StatefulDynamics` for a model with memory.
        step: the checkpoint step (chunks trained) the policy comes from.
        band: the calibrated error band of the kept policy
            (:class:`~jaxcal.calibrators.uncertainty.conformal.ThetaBand` of
            ``uncertainty.json``, fitted on the validation units at the end of
            training); ``None`` for a run without one.
        model_source: what the run stores of its model (``data.json``
            ``"model_source"``, :mod:`jaxcal.training.model_source`); ``None`` for a
            run of the older layout (its registered model's name, if it had one).
    """

    run_dir: Path
    config: Any
    problem: Any
    params: Any
    actor: Any
    dynamics: Any
    step: int
    band: Any = None
    model_source: dict | None = None

    @property
    def meta(self):
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


def run_problem(
    data: dict,
    model=None,
    run_dir: str | os.PathLike = ".",
    *,
    trust_code: bool = False,
) -> Problem:
    """The :class:`Problem` of a ``data.json`` dict (either layout).

    Args:
        data: the parsed ``data.json``.
        model: the model (``None``: the run's own,
            :func:`~jaxcal.training.model_source.load_run_model`).
        run_dir: the run folder ``data`` comes from (where its model copy lies).
        trust_code: consent to run the run's model copy or module.
    """
    model = model or load_run_model(run_dir, data, trust_code=trust_code)
    if "problem" in data:
        return Problem.from_json(data["problem"], model)
    # the older layout: RunMeta fields + the box and normalisation beside them,
    # mapped onto the current one
    ranges = ("w_low", "w_high", "x_low", "x_high")
    noise_std, noise_source = provisional_noise(data["norm"]["x_std"])
    current = {
        **{
            k: data[k] for k in ("theta_names", "theta_base", "theta_low", "theta_high")
        },
        "output_names": data["sensors"],
        "norm": data["norm"],
        "noise_std": noise_std,
        "noise_source": noise_source,
        "input_range": {k: data[k] for k in ranges}
        if data.get("w_low") is not None
        else None,
    }
    return Problem.from_json(current, model)


def load_run(
    run_dir: str | os.PathLike | LoadedRun,
    *,
    which: str = "selected",
    step: int | None = None,
    trust_code: bool = False,
) -> LoadedRun:
    """Load a run's policy.

    Args:
        run_dir: the run folder (a :class:`LoadedRun` passes through unchanged).
        which: ``"selected"``: the policy the run kept (``budget.select``: the best
            validation tracking RMSE, or the last one); ``"last"``: the latest
            checkpoint.
        step: a specific checkpoint step of ``which`` (``None``: the newest).
        trust_code: run the run's model code (its copy of a model file, or its
            module): the user trusts the folder. Not needed for a registered model,
            nor for a file the user named in this process (``docs/trust.md``).

    The model is the run's own (:mod:`jaxcal.training.model_source`: the copy of a
    model file kept in the folder, or a registered or installed module's by name),
    never a path outside the folder.

    Raises:
        FileNotFoundError: the folder is not a run, or it has no policy checkpoint.
        ValueError: the checkpoint does not match the run's config, the model
            cannot be loaded (its copy edited, or a file outside the folder), or it
            needs x64 and x64 is off; :class:`~jaxcal.trust.UntrustedCodeError` (a
            ValueError) naming the model copy and ``trust_code`` when its code needs
            the user's consent.
    """
    if isinstance(run_dir, LoadedRun):
        return run_dir
    if which not in ("selected", "last"):
        raise ValueError(f"which must be 'selected' or 'last', got {which!r}")
    run_dir = Path(run_dir)
    cfg = load_config(run_dir, TrainConfig)
    if needs_x64(run_dir):
        require_x64(f"run {run_dir}: dynamics=physics on a model that needs float64")
    data = read_json(run_dir / DATA_FILE)
    # its own model: never a path outside, its code only with the user's consent
    problem = run_problem(data, run_dir=run_dir, trust_code=trust_code)
    physics64 = cfg.dynamics == "physics" and problem.model.x64
    dtype = jnp.float64 if physics64 else jnp.float32
    dims = (
        len(problem.model.conditions), len(problem.output_names),
        len(problem.theta_names),
    )  # fmt: skip
    env_cfg = env_config(cfg, *dims)
    agent_cfg = agent_config(cfg, env_cfg)
    agent = make_agent(agent_cfg, env_cfg.observation_size, dims[2])
    target = _policy_target(cfg, env_cfg, agent, dims, dtype)
    step_given = step
    params, step = _restore_policy(run_dir, cfg, which, step, target)
    return LoadedRun(
        run_dir=run_dir,
        config=cfg,
        problem=problem,
        params=params,
        actor=make_networks(agent_cfg, dims[2]).actor,
        dynamics=make_dynamics(cfg.dynamics, problem),
        step=int(step),
        # the band belongs to the kept policy: none for another checkpoint
        band=load_band(run_dir) if which == "selected" and step_given is None else None,
        model_source=recorded_source(data),
    )


def _policy_target(cfg: TrainConfig, env_cfg, agent, dims, dtype):
    """The abstract :class:`PolicyParams` a run's checkpoint restores into (shapes
    and dtypes only, ``jax.eval_shape``): the class of the run's actions
    (incremental, with a start theta), the surrogate's weights with
    ``dynamics=surrogate``; ``dims = (W, S, P)``."""

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
            step_ref=jnp.ones(dims[2], dtype),
            max_increment=env_cfg.max_increment,
            x_noise=jnp.ones(dims[1], dtype) if env_cfg.gn_filter else None,
            **filter_settings(env_cfg),
        )
        if getattr(cfg.env, "start", "centre") == "prior":
            start = jnp.zeros(dims[2], dtype)
            return StartedIncrementPolicyParams(**fields, theta_start=start)
        return IncrementPolicyParams(**fields)

    return jax.eval_shape(abstract, jax.random.key(0))


def _restore_policy(run_dir: Path, cfg: TrainConfig, which: str, step, target):
    """``(params, step)``: the policy checkpoint ``step`` (``None``: the newest) of
    ``policy_best/`` (``which="selected"`` with selection on) or ``policy/``; the
    selected policy is the tuned one of ``policy_tuned/`` where the run holds one
    (``tune.steps``; its step is the chunk it was tuned from).

    Raises:
        FileNotFoundError: the folder holds no policy checkpoint.
    """
    folder = run_dir / POLICY_DIR
    best = run_dir / POLICY_BEST_DIR
    if which == "selected" and cfg.budget.select != "last" and best.is_dir():
        folder = best
    tuned = run_dir / POLICY_TUNED_DIR
    if which == "selected" and step is None and tuned.is_dir():
        folder = tuned
    with Checkpointer(folder) as ckpt:
        if ckpt.latest_step() is None:
            raise FileNotFoundError(
                f"{folder} holds no policy checkpoint; train the run "
                "first (python -m jaxcal.train ...)"
            )
        step = ckpt.latest_step() if step is None else step
        if folder == tuned and getattr(cfg.tune, "bias", False):
            # the tuned filter's output biases (tune.bias): their walk, one per output
            walk = jax.ShapeDtypeStruct(target.x_std.shape, target.x_std.dtype)
            target = with_output_states(target, walk)
        return ckpt.restore(step, target), step
