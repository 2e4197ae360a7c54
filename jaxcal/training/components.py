"""The machinery of a run, built from a config and the run's
:class:`~jaxcal.problem.Problem`.

* :func:`make_agent`: the SAC / LAC / CLAC factory the agent config asks for;
* :func:`make_dynamics`: the transition of the tracking MDP, either the learned
  surrogate D (``surrogate_apply``, the paper's choice) or the problem's model F
  (:meth:`Problem.measure`: declared parameters, used outputs, the others held at
  ``theta_base``); for a model with memory, its step with the state carried
  (:meth:`Problem.transition`, :class:`~jaxcal.envs.memory.StatefulDynamics`);
* :func:`make_components`: environment, agent and the two jitted entry points of a
  run (the training chunk and the fleet calibrator). They depend only on static,
  hashable choices, so they are cached per process: a resumed or repeated run in the
  same process (tests, sweeps) reuses the compiled code instead of recompiling.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.agents.clac import make_clac
from jaxcal.agents.common import Agent
from jaxcal.agents.configs import CLACConfig, LACConfig, SACConfig
from jaxcal.agents.lac import make_lac
from jaxcal.agents.networks import make_networks
from jaxcal.agents.sac import make_sac
from jaxcal.calibrators.methods.policy.calibrator import make_fleet_runner
from jaxcal.envs.memory import HintedDynamics, StatefulDynamics, transition_dynamics
from jaxcal.envs.tracking import Dynamics, Env, EnvConfig, make_tracking_env
from jaxcal.model import Model
from jaxcal.precision import require_x64
from jaxcal.problem import Problem
from jaxcal.surrogate.model import surrogate_apply
from jaxcal.training.runner import RunnerConfig, make_train_chunk
from jaxcal.typedefs import Array, PyTree


def make_agent(
    cfg: SACConfig | LACConfig | CLACConfig, observation_size: int, action_size: int
) -> Agent:
    """The agent of ``cfg``'s type (the exact type: CLACConfig subclasses LAC's)."""
    factories = {SACConfig: make_sac, LACConfig: make_lac, CLACConfig: make_clac}
    if type(cfg) not in factories:
        raise ValueError(
            f"agent config must be a SACConfig, LACConfig or CLACConfig, got "
            f"{type(cfg).__name__}"
        )
    return factories[type(cfg)](cfg, observation_size, action_size)


def env_config(cfg, condition_dim: int, sensor_dim: int, param_dim: int) -> EnvConfig:
    """The :class:`EnvConfig` of a run's
    :class:`~jaxcal.training.config.TrainConfig` and its data's dimensions (the one
    place the run-level ``env.*`` fields are mapped: those of the same name as they
    are, ``gauss_newton`` resolved)."""
    names = {f.name for f in dataclasses.fields(EnvConfig)} - {"gauss_newton"}
    same = {k: v for k, v in dataclasses.asdict(cfg.env).items() if k in names}
    return EnvConfig(
        sensor_dim=sensor_dim,
        condition_dim=condition_dim,
        param_dim=param_dim,
        gauss_newton=uses_gauss_newton(cfg.env, sensor_dim, param_dim),
        gn_filter=uses_filter(cfg.env),
        **same,
    )


def uses_gauss_newton(env, sensor_dim: int, param_dim: int) -> bool:
    """``env.gauss_newton`` resolved: ``"auto"`` is on for incremental actions when
    the outputs are at least as many as the parameters (one sample's Gauss-Newton
    step then determines theta)."""
    if env.gauss_newton in ("auto", "filter"):
        return env.action == "increment" and sensor_dim >= param_dim
    return env.gauss_newton == "on"


def agent_config(cfg, env_cfg: EnvConfig):
    """The run's agent config with the actor's prior: the share ``env.filter_gain``
    of the filter's step (``env.gauss_newton=filter``), which the observation holds
    just before the age (:func:`~jaxcal.envs.increment.gauss_newton_features`)."""
    if not env_cfg.gn_filter or not cfg.env.filter_gain:
        return cfg.agent
    start = env_cfg.observation_size - env_cfg.param_dim - 1
    prior = (start, float(cfg.env.filter_gain))
    return dataclasses.replace(cfg.agent, actor_prior=prior)


def uses_filter(env) -> bool:
    """``env.gauss_newton=filter`` with incremental actions: the observation also
    holds the filter's step (:func:`~jaxcal.envs.increment.filter_feature`),
    whatever the outputs' count. Unlike one sample's Gauss-Newton step (``auto``:
    outputs >= parameters), the filter gathers what the stream tells over time:
    the battery's one voltage tells R0 and Q apart, with the filter's random
    walk ``env.filter_q`` at the UKF's (``results/policy_any_model``)."""
    return env.gauss_newton == "filter" and env.action == "increment"


def make_dynamics(kind: str, problem: Problem) -> Dynamics | StatefulDynamics:
    """The transition ``dynamics(dyn_params, w_next, xhat, theta) -> xhat_next``.

    Args:
        kind: ``"surrogate"``: D with :class:`~jaxcal.surrogate.model.SurrogateParams`
            as ``dyn_params``; ``"physics"``: F(w_{t+1}, theta_{t+1}) of the
            problem's model on the declared parameters (the others at
            ``problem.theta_base``), ignoring ``xhat`` and ``dyn_params``. A model
            that needs float64 (``model.x64``, the turbofan's Newton solve) runs in
            float64 and needs x64 enabled; any other runs in the data's dtype. A
            model with memory gives a :class:`StatefulDynamics` (its step, the state
            carried; a stream's first state built with ``problem.theta_prior``).
        problem: the run's problem.

    Raises:
        ValueError: unknown kind, a float64 model with x64 disabled, or the
            surrogate asked of a model with memory.
    """
    return _dynamics(kind, *_dynamics_key(problem))


def _dynamics_key(problem: Problem) -> tuple:
    # Hashable, by value: a new Problem object of the same run reuses the cache.
    return (
        problem.model, problem.theta_names, problem.output_names,
        tuple(float(v) for v in problem.theta_base),
        tuple(float(v) for v in problem.theta_prior),
    )  # fmt: skip


def check_dynamics(kind: str, model: Model) -> None:
    """A clear error, before any work, for a dynamics the model cannot have.

    The surrogate D learns x_{t+1} = D(w_{t+1}, x_t, theta_{t+1}) in output space:
    the outputs of a model with memory do not determine its hidden state, so D
    would have to guess it, and the fitted transition (and every policy trained on
    it) would be biased without warning. Such a model trains on its own step.
    """
    if kind == "surrogate" and model.is_stateful:
        raise ValueError(
            f"dynamics=surrogate: model {model.name!r} has hidden states "
            f"{model.state_names} that its outputs do not determine, and the "
            "surrogate D (x_next = D(w_next, x, theta)) cannot carry them: use "
            "dynamics=physics"
        )
    if kind == "physics" and model.x64:
        require_x64(
            f"dynamics=physics: model {model.name!r} needs float64 (an iterative "
            "solver inside)"
        )


def _dynamics(kind, model, theta_names, output_names, theta_base, theta_prior):
    if kind not in ("surrogate", "physics"):
        raise ValueError(f"dynamics must be 'surrogate' or 'physics', got {kind!r}")
    check_dynamics(kind, model)
    if kind == "surrogate":
        return surrogate_apply
    if model.is_stateful:
        # The one restricted transition (Problem.transition); the box is not read.
        problem = Problem(
            model, tuple(theta_names), tuple(output_names), np.asarray(theta_base),
            None, None, None, None,
        )  # fmt: skip
        return transition_dynamics(problem.transition(), theta_prior, x64=model.x64)
    measure = model.restrict(theta_names, output_names, np.asarray(theta_base))

    def cast(w_next, xhat, theta):
        dtype = jnp.float64 if model.x64 else xhat.dtype
        return w_next.astype(dtype), theta.astype(dtype)

    def physics(dyn_params: PyTree, w_next: Array, xhat: Array, theta: Array):
        del dyn_params  # the model's constants are closed over
        return measure(*cast(w_next, xhat, theta)).astype(xhat.dtype)

    if not model.has_hint:
        return physics
    measure_hinted = model.restrict_hinted(
        theta_names, output_names, np.asarray(theta_base)
    )

    def physics_hinted(dyn_params, hint, w_next, xhat, theta):
        del dyn_params
        x, hint = measure_hinted(*cast(w_next, xhat, theta), hint)
        return hint, x.astype(xhat.dtype)

    # deployment may carry the model's solver warm start (training calls `physics`)
    return HintedDynamics(physics, physics_hinted, model.initial_hint)


class Components(NamedTuple):
    """The static machinery of a run.

    Attributes:
        env: the tracking environment.
        agent: the SAC / LAC / CLAC agent.
        actor: the agent's actor module (what deployment runs).
        dynamics: the environment's transition.
        train_chunk: ``jax.jit(make_train_chunk(env, agent, runner_cfg),
            donate_argnums=0)``.
        run_units: the jitted fleet calibrator
            (:func:`~jaxcal.calibrators.methods.policy.calibrator.make_fleet_runner`).
    """

    env: Env
    agent: Agent
    actor: nn.Module
    dynamics: Dynamics
    train_chunk: Callable
    run_units: Callable


def make_components(
    dynamics_kind: str,
    problem: Problem,
    env_cfg: EnvConfig,
    agent_cfg: SACConfig | LACConfig | CLACConfig,
    runner_cfg: RunnerConfig,
) -> Components:
    """Environment, agent and jitted entry points of a run (cached per process on
    the model object and the problem's names and base values)."""
    key = _dynamics_key(problem)
    return _components(dynamics_kind, key, env_cfg, agent_cfg, runner_cfg)


@functools.lru_cache(maxsize=8)
def _components(dynamics_kind, key, env_cfg, agent_cfg, runner_cfg) -> Components:
    dynamics = _dynamics(dynamics_kind, *key)
    env = make_tracking_env(dynamics, env_cfg)
    agent = make_agent(agent_cfg, env.observation_size, env.action_size)
    actor = make_networks(agent_cfg, env.action_size).actor
    return Components(
        env=env,
        agent=agent,
        actor=actor,
        dynamics=dynamics,
        train_chunk=jax.jit(make_train_chunk(env, agent, runner_cfg), donate_argnums=0),
        run_units=make_fleet_runner(actor, dynamics),
    )
