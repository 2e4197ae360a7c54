"""gymnasium wrapper: passes gymnasium's env checker; a random-action episode."""

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from support.norm import own_norm

from jaxcal.envs.gym_wrapper import TrackingGymEnv
from jaxcal.envs.tracking import EnvConfig, make_env_params, make_tracking_env

S, W, P, EPISODE = 3, 2, 1, 5


def dynamics(dyn_params, w_next, xhat, theta):
    del xhat
    return dyn_params["a"] @ w_next + dyn_params["b"] @ theta


@pytest.fixture(scope="module")
def gym_env():
    rng = np.random.default_rng(1)
    w, x = rng.normal(size=(2, 20, W)), rng.normal(size=(2, 20, S))
    dyn = {"a": rng.normal(size=(S, W)), "b": rng.normal(size=(S, P))}
    lengths = np.array([20, 15])
    params = make_env_params(
        w, x, lengths, [0.0], [2.0], dyn, stats=own_norm(w, x, lengths)
    )
    env = make_tracking_env(dynamics, EnvConfig(S, W, P, episode_length=EPISODE))
    return TrackingGymEnv(env, params, seed=0)


# Normalised observations are unbounded by nature; the checker warns about that.
@pytest.mark.filterwarnings("ignore:.*Box observation space m")
def test_wrapper_passes_gymnasium_env_checker(gym_env):
    check_env(gym_env, skip_render_check=True)


def test_random_action_episode_truncates_with_reward_minus_cost(gym_env):
    obs, info = gym_env.reset(seed=3)
    assert obs.dtype == np.float32 and gym_env.observation_space.contains(obs)
    steps, truncated = 0, False
    while not truncated:
        action = gym_env.action_space.sample()
        obs, reward, terminated, truncated, info = gym_env.step(action)
        steps += 1
        assert not terminated
        assert reward == pytest.approx(-info["cost"]) and reward <= 0.0
        assert 0.0 <= float(info["theta"][0]) <= 2.0
        assert gym_env.observation_space.contains(obs)
    assert steps == EPISODE


def test_reset_with_same_seed_is_reproducible(gym_env):
    first, _ = gym_env.reset(seed=11)
    second, _ = gym_env.reset(seed=11)
    np.testing.assert_array_equal(first, second)
    with pytest.raises(ValueError, match="shape"):
        gym_env.step(np.zeros(P + 1, np.float32))
