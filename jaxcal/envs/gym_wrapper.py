"""A gymnasium.Env view of one tracking environment, for SB3/SBX and other libraries.

The wrapper owns what gymnasium expects an env object to own (a PRNG key and the
current env state) and hands numpy to the caller; the dynamics run through the jitted
pure ``reset``/``step`` of :mod:`jaxcal.envs.tracking`. Reward = -cost; a tracking
window never terminates, it is truncated after ``episode_length`` steps.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import jax
import numpy as np

from jaxcal.envs.tracking import Env, EnvParams, check_env_params


class TrackingGymEnv(gym.Env):
    """gymnasium wrapper of one tracking environment instance.

    Args:
        env: the pure environment (:func:`~jaxcal.envs.tracking.make_tracking_env`).
        params: its data and dynamics parameters.
        seed: seed of the wrapper's PRNG key (``reset(seed=...)`` re-seeds it).

    Observation space: ``Box(-inf, inf, (O,), float32)``; action space
    ``Box(-1, 1, (P,), float32)`` (actions outside are clipped by the env's affine map).
    ``info`` carries ``theta`` (the parameters applied) and ``cost``.
    """

    metadata = {"render_modes": []}

    def __init__(self, env: Env, params: EnvParams, seed: int = 0) -> None:
        check_env_params(params, env.config)
        self._params = params
        self._reset = jax.jit(env.reset)
        self._step = jax.jit(env.step)
        self._key = jax.random.key(seed)
        self._state = None
        self.observation_space = gym.spaces.Box(
            -np.inf, np.inf, (env.observation_size,), np.float32
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (env.action_size,), np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Starts a new window at a random unit and start index."""
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.key(seed)
        self._key, key_reset = jax.random.split(self._key)
        obs, self._state = self._reset(key_reset, self._params)
        return np.asarray(obs, dtype=np.float32), {}

    def step(
        self, action: np.ndarray
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Applies theta(action) for one step: (obs, -cost, False, done, info)."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"action must have shape {self.action_space.shape}, got {action.shape}"
            )
        self._key, key_step = jax.random.split(self._key)
        obs, self._state, cost, done, info = self._step(
            key_step, self._state, action, self._params
        )
        cost = float(cost)
        info = {"theta": np.asarray(info["theta"]), "cost": cost}
        return np.asarray(obs, dtype=np.float32), -cost, False, bool(done), info
