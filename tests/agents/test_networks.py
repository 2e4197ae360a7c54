"""Policy and critic networks: non-negativity, squashed log-density, dtypes, shapes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxcal.agents.configs import LACConfig, SACConfig
from jaxcal.agents.networks import (
    make_networks,
    sample_squashed_gaussian,
    squashed_log_prob,
)

OBS, ACT = 5, 2


def test_lyapunov_critic_is_non_negative_for_random_inputs():
    critic = make_networks(LACConfig(critic_hidden_sizes=(8, 8)), ACT).critic
    key_init = jax.random.key(0)
    params = jax.jit(critic.init)(key_init, jnp.zeros((1, OBS)), jnp.zeros((1, ACT)))
    rng = np.random.default_rng(0)
    obs = 10.0 * rng.normal(size=(4096, OBS))
    action = rng.uniform(-1.0, 1.0, size=(4096, ACT))
    values = jax.jit(critic.apply)(params, obs, action)
    assert values.shape == (4096,)
    assert bool(jnp.all(values >= 0.0))
    assert float(values.max()) > 0.0


def test_squashed_log_prob_matches_change_of_variables():
    """log pi(tanh u) = log N(u; m, s) - log(d tanh/du), derivative by differences."""
    mean, log_std = np.float64(0.3), np.float64(-0.4)
    u = np.linspace(-3.0, 3.0, 41)
    ours = squashed_log_prob(
        jnp.asarray(u)[:, None],
        jnp.full((41, 1), mean),
        jnp.full((41, 1), log_std),
    )
    h = 1e-6
    dtanh = (np.tanh(u + h) - np.tanh(u - h)) / (2 * h)
    expected = stats.norm.logpdf(u, mean, np.exp(log_std)) - np.log(dtanh)
    np.testing.assert_allclose(np.asarray(ours), expected, rtol=1e-6, atol=1e-6)


def test_squashed_density_integrates_to_one():
    """Integrate pi(a) over a in (-1, 1) through a = tanh(u) on a fine grid."""
    mean, log_std = jnp.asarray([[0.5]]), jnp.asarray([[0.2]])
    a = np.linspace(-1 + 1e-9, 1 - 1e-9, 400_001)
    u = jnp.arctanh(jnp.asarray(a))[:, None]
    density = np.exp(np.asarray(squashed_log_prob(u, mean, log_std)))
    assert np.trapezoid(density, a) == pytest.approx(1.0, abs=1e-4)


def test_sampled_actions_stay_in_box_and_log_prob_is_finite():
    mean = jnp.asarray([[0.0, 8.0], [-8.0, 1.0]], jnp.float32)
    log_std = jnp.asarray([[2.0, 2.0], [2.0, -20.0]], jnp.float32)
    action, log_prob = sample_squashed_gaussian(jax.random.key(1), mean, log_std)
    assert bool(jnp.all(jnp.abs(action) <= 1.0))
    assert bool(jnp.all(jnp.isfinite(log_prob)))


def test_networks_are_float32_under_x64_and_shapes():
    networks = make_networks(
        SACConfig(actor_hidden_sizes=(8, 8), critic_hidden_sizes=(8, 8)), ACT
    )
    obs = jnp.ones((3, OBS), jnp.float64)
    action = jnp.zeros((3, ACT), jnp.float64)
    actor_params = jax.jit(networks.actor.init)(jax.random.key(0), obs)
    critic_params = jax.jit(networks.critic.init)(jax.random.key(1), obs, action)
    mean, log_std = jax.jit(networks.actor.apply)(actor_params, obs)
    q = jax.jit(networks.critic.apply)(critic_params, obs, action)
    assert mean.dtype == log_std.dtype == q.dtype == jnp.float32
    assert mean.shape == log_std.shape == (3, ACT)
    assert q.shape == (2, 3)
    # The twin critics are initialised independently.
    assert not np.allclose(q[0], q[1])
    for leaf in jax.tree.leaves((actor_params, critic_params)):
        assert leaf.dtype == jnp.float32


def test_log_std_is_clipped_to_config_range():
    networks = make_networks(
        SACConfig(actor_hidden_sizes=(8,), log_std_min=-1.0, log_std_max=0.5), ACT
    )
    params = networks.actor.init(jax.random.key(0), jnp.zeros((1, OBS)))
    _, log_std = networks.actor.apply(params, 1e3 * jnp.ones((2, OBS)))
    assert float(log_std.min()) >= -1.0
    assert float(log_std.max()) <= 0.5


def test_actor_prior_makes_an_untrained_mean_the_observed_steps_share():
    # actor_prior=(start, gain): the pre-tanh mean is arctanh(gain * obs[start:
    # start + A]) plus the network's own output (zero here), with no new parameter
    plain = make_networks(SACConfig(actor_hidden_sizes=(8,)), ACT).actor
    prior = make_networks(
        SACConfig(actor_hidden_sizes=(8,), actor_prior=(2, 0.5)), ACT
    ).actor
    obs = jnp.array([[0.1, -0.2, 0.8, -0.4, 0.3]])
    params = plain.init(jax.random.key(0), obs)
    assert jax.tree.structure(prior.init(jax.random.key(0), obs)) == jax.tree.structure(
        params
    )
    zero = jax.tree.map(jnp.zeros_like, params)
    mean, _ = prior.apply(zero, obs)
    np.testing.assert_allclose(jnp.tanh(mean), [[0.4, -0.2]], rtol=1e-5)
    mean_plain, _ = plain.apply(params, obs)
    mean_prior, _ = prior.apply(params, obs)
    np.testing.assert_allclose(
        mean_prior - mean_plain, jnp.arctanh(jnp.array([[0.4, -0.2]])), rtol=1e-5
    )
