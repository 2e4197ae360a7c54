"""Runner: one compilation per chunk, counters, update gating, evaluation, learning.

The mechanics and the learning sanity check share one training run (a module fixture)
so the suite compiles the CLAC chunk once: CLAC trains on 8 units of the analytic
calibration problem and is scored on 4 held-out units by the deterministic policy run
through whole trajectories, against the truth. The reference score is the RMSE of the
best constant guess (the training mean of theta).

The paper's multiplier schedule (initial temperature 2, log-temperature step 1e-4 per
update) needs ~1e5 updates before the entropy bonus stops dominating a cost of order
0.1; this budget is a few thousand updates, so the run starts from a small temperature
and uses larger learning rates. The slow test trains longer on a harder problem.
"""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.analytic import (
    analytic_dynamics,
    make_analytic_problem,
    problem_env_params,
)

from jaxcal.agents.clac import make_clac
from jaxcal.agents.common import Agent
from jaxcal.agents.configs import CLACConfig
from jaxcal.envs.tracking import EnvConfig, make_tracking_env
from jaxcal.problem import Normalisation
from jaxcal.training.runner import RunnerConfig, init_runner, make_train_chunk
from tests.support.policy_rollout import evaluate_policy

FAST_AGENT = dict(
    actor_lr=1e-3,
    critic_lr=1e-3,
    initial_entropy_temperature=0.01,
    entropy_temperature_lr=1e-3,
    initial_lyapunov_multiplier=1.0,
    gamma=0.9,
)
RUNNER = RunnerConfig(
    num_envs=8,
    num_steps_per_chunk=500,
    batch_size=128,
    buffer_size=50_000,
    warmup_steps=1000,
    min_buffer_size=1000,
)
EPISODE, NUM_TRAIN, NUM_TEST, T = 50, 8, 4, 200


def _problem(param_dim, interaction):
    make = jax.jit(
        make_analytic_problem,
        static_argnames=("num_units", "num_steps", "param_dim", "min_length"),
    )
    problem = make(
        jax.random.key(0),
        num_units=NUM_TRAIN + NUM_TEST,
        num_steps=T,
        param_dim=param_dim,
        interaction=interaction,
        min_length=150,
    )
    train = problem_env_params(problem, slice(0, NUM_TRAIN))
    stats = Normalisation(train.w_mean, train.w_std, train.x_mean, train.x_std)
    test = problem_env_params(problem, slice(NUM_TRAIN, None), stats)
    env = make_tracking_env(
        analytic_dynamics, EnvConfig(4, 2, param_dim, episode_length=EPISODE)
    )
    return problem, train, test, env


def _train(problem, train, test, env, *, num_chunks, hidden):
    agent = make_clac(
        CLACConfig(actor_hidden_sizes=hidden, critic_hidden_sizes=hidden, **FAST_AGENT),
        env.observation_size,
        env.action_size,
    )
    runner = jax.jit(init_runner, static_argnums=(1, 2, 4))(
        jax.random.key(1), env, agent, train, RUNNER
    )
    chex.clear_trace_counter()
    chunk = jax.jit(
        chex.assert_max_traces(make_train_chunk(env, agent, RUNNER), n=1),
        donate_argnums=0,
    )
    history = []
    for _ in range(num_chunks):
        runner, metrics = chunk(runner, train)
        history.append(jax.device_get(metrics))
    out = jax.jit(evaluate_policy, static_argnums=(1, 2))(
        jax.random.key(2), env, agent, runner.agent_state, test
    )
    return runner, history, out


def _scores(problem, out):
    mask = np.asarray(out.mask)
    truth = np.asarray(problem.theta[NUM_TRAIN:])
    rmse = np.sqrt(np.mean((np.asarray(out.theta) - truth)[mask] ** 2))
    lengths = np.asarray(problem.lengths[:NUM_TRAIN])
    train_mask = np.arange(T)[None] < lengths[:, None]
    prior = np.asarray(problem.theta[:NUM_TRAIN])[train_mask].mean(0)
    return rmse, np.sqrt(np.mean((truth[mask] - prior) ** 2))


@pytest.fixture(scope="module")
def linear_run():
    problem, train, test, env = _problem(param_dim=1, interaction=0.0)
    runner, history, out = _train(
        problem, train, test, env, num_chunks=10, hidden=(64, 64)
    )
    return problem, runner, history, out


def test_train_chunk_compiles_once_and_counts(linear_run):
    _, runner, history, _ = linear_run
    # 10 chunks ran through a function that may be traced only once.
    assert len(history) == 10
    for metrics in history:
        chex.assert_tree_all_finite(metrics)
    first, last = history[0], history[-1]
    per_chunk = RUNNER.num_envs * RUNNER.num_steps_per_chunk
    assert (
        int(first["env_steps"]) == per_chunk
        and int(last["env_steps"]) == 10 * per_chunk
    )
    # Updates start once 1000 transitions (125 iterations of 8 envs) are stored.
    assert int(first["num_updates"]) == 500 - 124
    assert int(last["num_updates"]) == 10 * 500 - 124 == int(runner.agent_state.step)
    assert int(last["buffer_size"]) == 10 * per_chunk
    # Each env finishes an episode every EPISODE steps and is reset.
    assert int(first["episodes"]) == per_chunk // EPISODE
    assert float(last["cost"]) < float(first["cost"])


def test_clac_recovers_theta_on_held_out_units(linear_run):
    problem, _, history, out = linear_run
    rmse, baseline = _scores(problem, out)
    # theta lives in a unit box: within 10 % of the range and well below the spread
    # (seeded run: rmse 0.035 against a spread of 0.128).
    assert rmse < 0.1, (rmse, baseline)
    assert rmse < 0.5 * baseline, (rmse, baseline)
    assert float(history[-1]["cost"]) < 0.05


# make test-long: 40 chunks on a nonlinear two-parameter problem; the same training
# and scoring in make test: test_clac_recovers_theta_on_held_out_units
@pytest.mark.slow
def test_clac_recovers_two_parameters_on_nonlinear_problem():
    problem, train, test, env = _problem(param_dim=2, interaction=0.3)
    _, _, out = _train(problem, train, test, env, num_chunks=40, hidden=(64, 64))
    rmse, baseline = _scores(problem, out)
    # Seeded run: rmse 0.023 against a spread of 0.144.
    assert rmse < 0.05, (rmse, baseline)
    assert rmse < 0.25 * baseline, (rmse, baseline)


def _oracle_agent(problem, params, env):
    """Inverts the linear model from the observation: the exact calibration policy."""
    dyn = problem.dyn_params
    b_pinv = jnp.linalg.pinv(dyn.b)

    def act(key, agent_state, obs, deterministic=False):
        x_next = obs[4:8] * params.x_std + params.x_mean
        w_next = obs[8:10] * params.w_std + params.w_mean
        theta = b_pinv @ (x_next - dyn.a @ w_next - dyn.c)
        box = params.theta_high - params.theta_low
        return 2.0 * (theta - params.theta_low) / box - 1.0

    return Agent(lambda key: None, act, None, env.observation_size, env.action_size)


def test_evaluate_policy_aligns_theta_xhat_and_masks_padding():
    problem = jax.jit(
        make_analytic_problem, static_argnames=("num_units", "num_steps", "min_length")
    )(jax.random.key(0), num_units=3, num_steps=24, min_length=12)
    params = problem_env_params(problem, slice(None))
    env = make_tracking_env(analytic_dynamics, EnvConfig(4, 2, 1, episode_length=5))
    agent = _oracle_agent(problem, params, env)
    out = jax.jit(evaluate_policy, static_argnums=(1, 2))(
        jax.random.key(0), env, agent, None, params
    )
    mask = np.arange(24)[None] < np.asarray(problem.lengths)[:, None]
    np.testing.assert_array_equal(out.mask, mask)
    assert out.theta.shape == (3, 24, 1) and out.xhat.shape == (3, 24, 4)
    later = mask.copy()
    later[:, 0] = False
    np.testing.assert_allclose(
        np.asarray(out.theta)[later], np.asarray(problem.theta)[later], atol=1e-6
    )
    np.testing.assert_array_equal(out.theta[:, 0], out.theta[:, 1])
    np.testing.assert_allclose(
        np.asarray(out.xhat)[mask], np.asarray(problem.x)[mask], atol=1e-6
    )
    assert float(jnp.max(out.cost)) < 1e-8
    assert np.all(np.asarray(out.theta)[~mask] == 0)
    assert np.all(np.asarray(out.xhat)[~mask] == 0)


def test_runner_config_and_init_reject_bad_input():
    with pytest.raises(ValueError, match="num_envs"):
        RunnerConfig(num_envs=0)
    with pytest.raises(ValueError, match="buffer_size"):
        RunnerConfig(num_envs=8, buffer_size=4)
    env = make_tracking_env(analytic_dynamics, EnvConfig(4, 2, 1, episode_length=5))
    agent = make_clac(
        CLACConfig(actor_hidden_sizes=(4,), critic_hidden_sizes=(4,)), 3, 1
    )
    with pytest.raises(ValueError, match="observation_size"):
        init_runner(jax.random.key(0), env, agent, None, RunnerConfig(num_envs=2))
