"""SAC / LAC / CLAC agents: one compiled update, finite metrics, targets, clips."""

import collections

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.agents.buffer import Transition
from jaxcal.agents.clac import make_clac
from jaxcal.agents.configs import CLACConfig, LACConfig, SACConfig
from jaxcal.agents.lac import make_lac
from jaxcal.agents.sac import make_sac

OBS, ACT, B = 6, 2, 16
TINY = dict(actor_hidden_sizes=(8, 8), critic_hidden_sizes=(8, 8))
AGENTS = {
    "sac": (make_sac, SACConfig(**TINY)),
    "lac": (make_lac, LACConfig(**TINY)),
    "clac": (make_clac, CLACConfig(**TINY)),
}


def _batch(key):
    keys = jax.random.split(key, 4)
    return Transition(
        obs=jax.random.normal(keys[0], (B, OBS), jnp.float32),
        action=jax.random.uniform(keys[1], (B, ACT), jnp.float32, -1.0, 1.0),
        cost=jax.random.uniform(keys[2], (B,), jnp.float32),
        next_obs=jax.random.normal(keys[3], (B, OBS), jnp.float32),
        terminal=jnp.zeros((B,), jnp.float32),
    )


def _counting_traces(fn, traces, name):
    def traced(*args):
        traces[name] += 1  # Python runs here only while jax.jit traces
        return fn(*args)

    return traced


@pytest.fixture(scope="module")
def compiled():
    """One agent and one jitted update per algorithm, shared, and the number of times
    each update was traced. (chex.assert_max_traces keys its counter on the function's
    source, and the three agents' updates share theirs: the shared actor-critic one.)
    """
    traces = collections.Counter()
    out = {}
    for name, (make, cfg) in AGENTS.items():
        agent = make(cfg, OBS, ACT)
        out[name] = (agent, jax.jit(_counting_traces(agent.update, traces, name)))
    return out, traces


@pytest.mark.parametrize("name", sorted(AGENTS))
def test_update_compiles_once_and_gives_finite_metrics(name, compiled):
    agents, traces = compiled
    agent, update = agents[name]
    tau = AGENTS[name][1].tau
    state = agent.init(jax.random.key(0))
    first, metrics = update(jax.random.key(1), state, _batch(jax.random.key(2)))
    second, metrics = update(jax.random.key(3), first, _batch(jax.random.key(4)))
    assert int(second.step) == 2
    assert traces[name] == 1
    chex.assert_tree_all_finite((second, metrics))
    assert np.isfinite(float(metrics["critic_loss"]))
    # Online parameters moved, targets followed by exactly tau (Polyak, Algorithm 1).
    moved = jax.tree.map(
        lambda a, b: not np.allclose(a, b), first.critic.params, second.critic.params
    )
    assert any(jax.tree.leaves(moved))
    expected_target = jax.tree.map(
        lambda t, o: (1 - tau) * t + tau * o,
        first.target_critic_params,
        second.critic.params,
    )
    chex.assert_trees_all_close(second.target_critic_params, expected_target, rtol=1e-6)


@pytest.mark.parametrize("name", sorted(AGENTS))
def test_act_returns_actions_in_box(name):
    make, cfg = AGENTS[name]
    agent = make(cfg, OBS, ACT)
    state = agent.init(jax.random.key(0))
    obs = 5.0 * jax.random.normal(jax.random.key(1), (32, OBS))
    action = agent.act(jax.random.key(2), state, obs)
    greedy = agent.act(jax.random.key(2), state, obs, deterministic=True)
    again = agent.act(jax.random.key(9), state, obs, deterministic=True)
    assert action.shape == greedy.shape == (32, ACT)
    assert bool(jnp.all(jnp.abs(action) <= 1.0))
    np.testing.assert_array_equal(greedy, again)
    assert not np.allclose(action, greedy)


def test_multipliers_are_clipped_and_move_the_right_way(compiled):
    agent, update = compiled[0]["clac"]
    state = agent.init(jax.random.key(0))
    # Start just below the clip: Adam's first step (size lr, 1e-4 in log space) would
    # overshoot lambda = 1 unless the update projects it back.
    state = state.replace(
        log_lyapunov_multiplier=state.log_lyapunov_multiplier.replace(
            params=jnp.asarray(-1e-5, jnp.float32)
        )
    )
    # Costs of 10 make the Lyapunov decrease Delta positive: lambda must rise to 1.
    batch = _batch(jax.random.key(1))._replace(cost=jnp.full((B,), 10.0, jnp.float32))
    new_state, metrics = update(jax.random.key(2), state, batch)
    assert float(metrics["lyapunov_decrease"]) > 0
    assert float(new_state.log_lyapunov_multiplier.params) == 0.0
    # The smoothness multiplier moves against the sign of (action change - threshold).
    change = float(metrics["action_change"]) - AGENTS["clac"][1].smoothness_threshold
    step = float(
        new_state.log_smoothness_multiplier.params
        - state.log_smoothness_multiplier.params
    )
    assert np.sign(step) == np.sign(change) != 0


def test_temperature_initial_value_and_target_entropy():
    cfg = LACConfig(**TINY)
    state = make_lac(cfg, OBS, ACT).init(jax.random.key(0))
    assert float(jnp.exp(state.log_entropy_temperature.params)) == pytest.approx(2.0)
    assert float(jnp.exp(state.log_lyapunov_multiplier.params)) == pytest.approx(0.1)
    assert cfg.resolved_target_entropy(ACT) == -ACT


def test_configs_and_factories_reject_bad_input():
    with pytest.raises(ValueError, match="gamma"):
        LACConfig(gamma=1.0)
    with pytest.raises(ValueError, match="actor_hidden_sizes"):
        SACConfig(actor_hidden_sizes=())
    with pytest.raises(ValueError, match="initial_lyapunov_multiplier"):
        LACConfig(initial_lyapunov_multiplier=2.0)
    with pytest.raises(ValueError, match="LACConfig"):
        make_lac(CLACConfig(), OBS, ACT)
    with pytest.raises(ValueError, match="observation_size"):
        make_sac(SACConfig(), 0, ACT)
