"""Tracking MDP: windows, observation and cost formulas, done flags, tracing, gradients.

The fixture pads units with NaN after their length, so any read of a padded row shows
up as a non-finite output.
"""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.norm import own_norm

from jaxcal.envs.tracking import (
    EnvConfig,
    check_env_params,
    make_env_params,
    make_tracking_env,
)
from jaxcal.problem import Normalisation

U, T, S, W, P = 3, 12, 3, 2, 2
LENGTHS = np.array([12, 9, 5])
EPISODE = 4  # a window needs EPISODE + 2 = 6 rows: unit 2 (5 rows) is never drawn


def dynamics(dyn_params, w_next, xhat, theta):
    """A surrogate-like map that uses all three inputs."""
    return 0.5 * xhat + dyn_params["b"] @ theta + jnp.sum(w_next) * dyn_params["c"]


@pytest.fixture(scope="module")
def tiny():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(U, T, W)) * [1.0, 3.0] + [0.5, -2.0]
    x = rng.normal(size=(U, T, S)) * [2.0, 0.5, 1.0] + 10.0
    valid = (np.arange(T)[None] < LENGTHS[:, None])[..., None]
    w, x = np.where(valid, w, np.nan), np.where(valid, x, np.nan)
    dyn_params = {"b": jnp.asarray(rng.normal(size=(S, P))), "c": jnp.ones(S)}
    params = make_env_params(
        w, x, LENGTHS, np.array([0.0, -1.0]), np.array([1.0, 3.0]), dyn_params,
        stats=own_norm(w, x, LENGTHS),
    )  # fmt: skip
    env = make_tracking_env(
        dynamics,
        EnvConfig(sensor_dim=S, condition_dim=W, param_dim=P, episode_length=EPISODE),
    )
    return env, params, w, x


def _norm(value, mean, std):
    return (value - np.asarray(mean)) / np.asarray(std)


def test_reset_draws_windows_inside_valid_length(tiny):
    env, params, w, x = tiny
    keys = jax.random.split(jax.random.key(0), 512)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    unit, start = np.asarray(state.unit), np.asarray(state.time)
    assert obs.shape == (512, env.observation_size) and obs.dtype == jnp.float32
    assert set(unit.tolist()) == {0, 1}
    assert np.all(start >= 0)
    assert np.all(start + EPISODE + 1 <= LENGTHS[unit] - 1)
    # Both the first and the last admissible starts of unit 0 occur.
    assert {0, LENGTHS[0] - EPISODE - 2} <= set(start[unit == 0].tolist())
    np.testing.assert_allclose(state.xhat, x[unit, start])
    np.testing.assert_array_equal(state.step, 0)
    assert np.all(np.isfinite(obs))


def test_step_applies_theta_and_computes_cost_and_next_obs(tiny):
    env, params, w, x = tiny
    _, state = env.reset_at(params, 1, 2)
    action = jnp.asarray([-1.0, 1.0])
    obs, next_state, cost, done, info = env.step(
        jax.random.key(0), state, action, params
    )
    theta = np.array([0.0, 3.0])
    np.testing.assert_allclose(info["theta"], theta)
    xhat = 0.5 * x[1, 2] + np.asarray(params.dyn_params["b"]) @ theta + w[1, 3].sum()
    np.testing.assert_allclose(next_state.xhat, xhat)
    x_std = np.asarray(params.x_std)
    assert float(cost) == pytest.approx(np.mean(((x[1, 3] - xhat) / x_std) ** 2), 1e-5)
    expected_obs = np.concatenate(
        [
            _norm(xhat, params.x_mean, x_std),
            _norm(x[1, 4], params.x_mean, x_std),
            _norm(w[1, 4], params.w_mean, params.w_std),
        ]
    )
    np.testing.assert_allclose(obs, expected_obs, rtol=1e-5)
    assert int(next_state.time) == 3 and int(next_state.step) == 1
    assert not bool(done) and not bool(info["terminated"])


def test_action_map_is_affine_and_clips():
    from jaxcal.envs.tracking import action_to_theta

    class Box:
        theta_low = jnp.asarray([0.0, -1.0])
        theta_high = jnp.asarray([1.0, 3.0])

    np.testing.assert_allclose(
        action_to_theta(jnp.asarray([0.0, 0.5]), Box), [0.5, 2.0]
    )
    np.testing.assert_allclose(
        action_to_theta(jnp.asarray([-3.0, 3.0]), Box), [0.0, 3.0]
    )


def test_episode_is_truncated_after_episode_length(tiny):
    env, params, _, _ = tiny
    step = jax.jit(env.step)
    obs, state = env.reset(jax.random.key(3), params)
    dones = []
    for i in range(EPISODE):
        obs, state, cost, done, info = step(
            jax.random.key(i), state, jnp.zeros(P), params
        )
        dones.append(bool(done))
        assert bool(info["truncated"]) == bool(done)
        assert np.isfinite(float(cost)) and np.all(np.isfinite(obs))
    assert dones == [False] * (EPISODE - 1) + [True]


def test_step_compiles_once(tiny):
    env, params, _, _ = tiny
    chex.clear_trace_counter()
    step = jax.jit(chex.assert_max_traces(env.step, n=1))
    _, state = env.reset_at(params, 0, 0)
    _, state, *_ = step(jax.random.key(0), state, jnp.zeros(P), params)
    _, state, *_ = step(jax.random.key(1), state, jnp.ones(P), params)
    assert int(state.step) == 2


def test_step_near_unit_end_never_reads_padding(tiny):
    env, params, _, _ = tiny
    obs, state = env.reset_at(params, 2, LENGTHS[2] - 1)
    assert np.all(np.isfinite(obs))
    obs, state, cost, *_ = env.step(jax.random.key(0), state, jnp.zeros(P), params)
    assert np.all(np.isfinite(obs)) and np.isfinite(float(cost))


def test_transition_gradient_is_stopped_unless_enabled(tiny):
    _, params, _, _ = tiny

    def cost_of(env, action):
        _, state = env.reset_at(params, 0, 1)
        return env.step(jax.random.key(0), state, action, params)[2]

    cfg = dict(sensor_dim=S, condition_dim=W, param_dim=P, episode_length=EPISODE)
    stopped = make_tracking_env(dynamics, EnvConfig(**cfg))
    open_env = make_tracking_env(dynamics, EnvConfig(**cfg, differentiable=True))
    action = jnp.asarray([0.2, -0.3])
    np.testing.assert_array_equal(jax.grad(lambda a: cost_of(stopped, a))(action), 0.0)
    assert float(jnp.abs(jax.grad(lambda a: cost_of(open_env, a))(action)).sum()) > 0


def test_env_normalises_with_the_given_stats_only(tiny):
    """The env never computes a normalisation: it takes the given one (a run's
    problem's), cast to the data's dtype, and refuses a non-positive or missized
    std."""
    _, params, w, x = tiny
    other = Normalisation(
        np.array([1.5, -0.5]), np.array([2.0, 4.0]), np.full(S, 3.0), np.full(S, 0.5)
    )
    box = (np.array([0.0, -1.0]), np.array([1.0, 3.0]))
    given = make_env_params(w, x, LENGTHS, *box, params.dyn_params, stats=other)
    for name, value in other._asdict().items():
        got = getattr(given, name)
        assert got.dtype == jnp.asarray(x).dtype
        np.testing.assert_array_equal(got, jnp.asarray(value, got.dtype))
    for bad in (other._replace(x_std=np.zeros(S)), other._replace(w_std=np.ones(3))):
        with pytest.raises(ValueError, match="stats"):
            make_env_params(w, x, LENGTHS, *box, params.dyn_params, stats=bad)
    with pytest.raises(TypeError, match="stats"):
        make_env_params(w, x, LENGTHS, *box, params.dyn_params)


def test_make_env_params_rejects_bad_input(tiny):
    _, params, w, x = tiny
    low, high = np.zeros(P), np.ones(P)
    dyn = params.dyn_params
    stats = own_norm(w, x, LENGTHS)
    with pytest.raises(ValueError, match="lengths"):
        make_env_params(w, x, np.array([12, 9, 13]), low, high, dyn, stats=stats)
    with pytest.raises(ValueError, match="theta_low"):
        make_env_params(w, x, LENGTHS, high, low, dyn, stats=stats)
    with pytest.raises(ValueError, match=r"\[U, T, W\]"):
        make_env_params(w[0], x, LENGTHS, low, high, dyn, stats=stats)
    bad = x.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        make_env_params(w, bad, LENGTHS, low, high, dyn, stats=stats)


def test_check_env_params_rejects_mismatch_and_short_units(tiny):
    _, params, _, _ = tiny
    with pytest.raises(ValueError, match="episode_length"):
        check_env_params(params, EnvConfig(S, W, P, episode_length=11))
    with pytest.raises(ValueError, match="EnvParams.x"):
        check_env_params(params, EnvConfig(S + 1, W, P, episode_length=2))
    with pytest.raises(ValueError, match="episode_length"):
        EnvConfig(S, W, P, episode_length=0)


def test_cost_compares_with_x_target_when_given(tiny):
    """Simulated units: the cost's target is their noise-free outputs, the
    observation still the noisy ones."""
    env, params, w, x = tiny
    target = np.where(np.isfinite(x), x + 0.25, np.nan)
    with_target = make_env_params(
        w, x, LENGTHS, np.array([0.0, -1.0]), np.array([1.0, 3.0]),
        params.dyn_params, stats=own_norm(w, x, LENGTHS), x_target=target,
    )  # fmt: skip
    action = jnp.asarray([0.3, -0.2])
    costs, observations = [], []
    for p in (params, with_target):
        _, state = env.reset_at(p, 1, 2)
        obs, nxt, cost, _, _ = env.step(jax.random.key(0), state, action, p)
        costs.append(float(cost)), observations.append(np.asarray(obs))
        xhat = np.asarray(nxt.xhat)
    np.testing.assert_array_equal(observations[0], observations[1])
    x_std = np.asarray(params.x_std)
    expect = np.mean(((target[1, 3] - xhat) / x_std) ** 2)
    assert costs[1] == pytest.approx(expect, 1e-5) and costs[1] != costs[0]
    with pytest.raises(ValueError, match="x_target"):
        make_env_params(
            w, x, LENGTHS, np.array([0.0, -1.0]), np.array([1.0, 3.0]),
            params.dyn_params, stats=own_norm(w, x, LENGTHS), x_target=target[:, :5],
        )  # fmt: skip


def test_theta_cost_adds_the_known_theta_error_to_the_cost(tiny):
    """env.theta_cost (issue 41): where the true theta is known (a simulated unit's),
    the cost adds theta_cost * mean_P(((theta - truth) / h)^2); rows of unknown
    truth (NaN: a real unit's) cost what tracking costs."""
    _, params, w, x = tiny
    truth = np.zeros((U, T, P))
    truth[0] = [0.25, 0.5]  # unit 0 known; unit 1 half known; unit 2 unknown
    truth[1, :, 1] = np.nan
    truth[2] = np.nan
    cfg = EnvConfig(sensor_dim=S, condition_dim=W, param_dim=P, episode_length=EPISODE)
    weighted = EnvConfig(**{**cfg.__dict__, "theta_cost": 2.0})
    with_truth = make_env_params(
        w, x, LENGTHS, np.array([0.0, -1.0]), np.array([1.0, 3.0]), params.dyn_params,
        stats=own_norm(w, x, LENGTHS), theta_target=truth,
    )  # fmt: skip
    action = jnp.array([0.5, -0.5])  # the same theta in every case
    costs = {}
    for name, conf, prm in [
        ("plain", cfg, with_truth),
        ("weighted", weighted, with_truth),
        ("no truth", weighted, params),
    ]:
        env = make_tracking_env(dynamics, conf)
        for unit in range(2):
            _, state = env.reset_at(prm, unit, 1)
            _, _, cost, _, info = env.step(jax.random.key(0), state, action, prm)
            costs[name, unit] = (float(cost), np.asarray(info["theta"]))
    half = np.array([0.5, 2.0])
    for unit, known in [(0, [0, 1]), (1, [0])]:
        theta = costs["plain", unit][1]
        err = ((theta - truth[unit, 2]) / half)[known]
        extra = 2.0 * float(np.mean(err**2))
        assert extra > 0
        np.testing.assert_allclose(
            costs["weighted", unit][0], costs["plain", unit][0] + extra, rtol=1e-5
        )
        assert costs["no truth", unit][0] == pytest.approx(costs["plain", unit][0])
    with pytest.raises(ValueError, match="theta_target must be shaped"):
        make_env_params(
            w, x, LENGTHS, np.array([0.0, -1.0]), np.array([1.0, 3.0]),
            params.dyn_params, stats=own_norm(w, x, LENGTHS),
            theta_target=truth[:, :, :1],
        )  # fmt: skip
