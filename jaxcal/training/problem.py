"""The pieces of a calibration problem, built from a config and the run's data.

* :func:`make_agent`: the SAC / LAC / CLAC factory the agent config asks for;
* :func:`make_dynamics`: the transition of the tracking MDP, either the learned
  surrogate D (``surrogate_apply``, the paper's choice) or the physics F of the data
  set's engine with the undeclared parameters held at their dev mean;
* :class:`RunMeta`: what a deployed policy needs to know about the data (sensor and
  parameter names, engine, the undeclared parameters' values), stored in ``data.json``;
* :func:`make_components`: environment, agent and the two jitted entry points of a
  run (the training chunk and the fleet calibrator). They depend only on static,
  hashable choices, so they are cached per process: a resumed or repeated run in the
  same process (tests, sweeps) reuses the compiled code instead of recompiling.
"""

from __future__ import annotations

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
from jaxcal.calibrators.policy import make_fleet_runner
from jaxcal.envs.tracking import Dynamics, Env, EnvConfig, make_tracking_env
from jaxcal.surrogate.model import surrogate_apply
from jaxcal.training.data import CalibrationData
from jaxcal.training.runner import RunnerConfig, make_train_chunk
from jaxcal.typedefs import Array, PyTree


class RunMeta(NamedTuple):
    """Data-set facts a policy is tied to (JSON round trip via ``_asdict``).

    Attributes:
        sensors: S sensor names, in observation order.
        theta_names: P declared parameter names, in action order.
        engine: engine configuration name (for ``dynamics=physics``).
        theta_base: the 10 health modifiers; undeclared ones are held here.
        condition_dim: W.
        w_low, w_high, x_low, x_high: ``[W]`` / ``[S]`` min and max of the training
            units' valid samples (the deployed input check, see
            :func:`jaxcal.calibrators.policy.range_check`); ``None`` for runs
            written before they were stored.
    """

    sensors: tuple[str, ...]
    theta_names: tuple[str, ...]
    engine: str
    theta_base: tuple[float, ...]
    condition_dim: int
    w_low: tuple[float, ...] | None = None
    w_high: tuple[float, ...] | None = None
    x_low: tuple[float, ...] | None = None
    x_high: tuple[float, ...] | None = None

    @classmethod
    def from_data(cls, data: CalibrationData) -> RunMeta:
        """The meta of a loaded data set."""
        return cls(
            sensors=tuple(data.sensors),
            theta_names=tuple(data.theta_names),
            engine=data.engine,
            theta_base=tuple(float(v) for v in data.theta_base),
            condition_dim=int(data.train.w.shape[-1]),
            **_training_range(data.train.w, data.train.x, data.train.mask),
        )

    @classmethod
    def from_json(cls, data: dict) -> RunMeta:
        """Inverse of ``_asdict`` after a JSON round trip."""
        return cls(
            sensors=tuple(data["sensors"]),
            theta_names=tuple(data["theta_names"]),
            engine=str(data["engine"]),
            theta_base=tuple(float(v) for v in data["theta_base"]),
            condition_dim=int(data["condition_dim"]),
            **{
                name: tuple(float(v) for v in data[name])
                for name in ("w_low", "w_high", "x_low", "x_high")
                if data.get(name) is not None
            },
        )


def _training_range(w, x, mask) -> dict[str, tuple[float, ...]]:
    """Per-column min / max of the valid rows of ``w [U, T, W]``, ``x [U, T, S]``."""
    rows = np.asarray(mask, bool)
    w, x = np.asarray(w, np.float64)[rows], np.asarray(x, np.float64)[rows]
    as_tuple = lambda a: tuple(float(v) for v in a)  # noqa: E731 (hashable meta)
    return {
        "w_low": as_tuple(w.min(axis=0)),
        "w_high": as_tuple(w.max(axis=0)),
        "x_low": as_tuple(x.min(axis=0)),
        "x_high": as_tuple(x.max(axis=0)),
    }


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


def make_dynamics(kind: str, meta: RunMeta) -> Dynamics:
    """The transition ``dynamics(dyn_params, w_next, xhat, theta) -> xhat_next``.

    Args:
        kind: ``"surrogate"``: D with :class:`~jaxcal.surrogate.model.SurrogateParams`
            as ``dyn_params``; ``"physics"``: F(w_{t+1}, theta_{t+1}) of
            ``meta.engine`` on the declared parameters (undeclared ones at
            ``meta.theta_base``), ignoring ``xhat`` and ``dyn_params``. The engine
            solves in float64: enable x64 before calling it.
        meta: the run's data facts.

    Raises:
        ValueError: unknown kind.
    """
    if kind == "surrogate":
        return surrogate_apply
    if kind != "physics":
        raise ValueError(f"dynamics must be 'surrogate' or 'physics', got {kind!r}")
    # Imported here: the engine loads its design tables, which surrogate runs skip.
    from jaxcal.calibrators.interface import measure_declared
    from jaxcal.physics import load_engine

    engine = load_engine(meta.engine)
    measure = measure_declared(
        lambda w, theta: engine.evaluate(w, theta)[0],
        np.asarray(meta.theta_base),
        meta.theta_names,
        meta.sensors,
    )

    def physics(dyn_params: PyTree, w_next: Array, xhat: Array, theta: Array):
        del dyn_params  # the engine's constants are closed over
        x = measure(w_next.astype(jnp.float64), theta.astype(jnp.float64))
        return x.astype(xhat.dtype)

    return physics


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
            (:func:`~jaxcal.calibrators.policy.make_fleet_runner`).
    """

    env: Env
    agent: Agent
    actor: nn.Module
    dynamics: Dynamics
    train_chunk: Callable
    run_units: Callable


@functools.lru_cache(maxsize=8)
def make_components(
    dynamics_kind: str,
    meta: RunMeta,
    env_cfg: EnvConfig,
    agent_cfg: SACConfig | LACConfig | CLACConfig,
    runner_cfg: RunnerConfig,
) -> Components:
    """Environment, agent and jitted entry points of a run (cached per process)."""
    dynamics = make_dynamics(dynamics_kind, meta)
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
