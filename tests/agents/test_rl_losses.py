"""SAC / LAC / CLAC losses against a float64 numpy re-implementation on tiny arrays.

The networks have one hidden layer of 3 units with fixed (seeded) weights; the numpy
reference recomputes every forward pass by hand and draws the same Gaussian noise from
the same keys as the losses document (one key per sampled action, ``split(key)`` into
``(key_now, key_next)`` in the LAC/CLAC actor losses).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.agents import losses
from jaxcal.agents.buffer import Transition
from jaxcal.agents.configs import LACConfig, SACConfig
from jaxcal.agents.networks import deterministic_action, make_networks

B, OBS, ACT = 4, 3, 2
SLOPE = 0.2


def _np(tree):
    return jax.tree.map(lambda x: np.asarray(x, np.float64), tree)


def _leaky(x):
    return np.where(x >= 0, x, SLOPE * x)


def _dense(p, x):
    return x @ p["kernel"] + p["bias"]


def _actor(params, obs):
    p = _np(params)["params"]
    h = _leaky(_dense(p["MLP_0"]["Dense_0"], obs))
    return _dense(p["Dense_0"], h), np.clip(_dense(p["Dense_1"], h), -20.0, 2.0)


def _lyapunov(params, obs, action):
    p = _np(params)["params"]
    h = _leaky(_dense(p["MLP_0"]["Dense_0"], np.concatenate([obs, action], -1)))
    return np.sum(h**2, -1)


def _twin_q(params, obs, action):
    p = _np(params)["params"]["VmapQCritic_0"]
    x = np.concatenate([obs, action], -1)
    out = []
    for i in range(2):
        layer = jax.tree.map(lambda a, i=i: a[i], p)
        h = _leaky(_dense(layer["MLP_0"]["Dense_0"], x))
        out.append(_dense(layer["Dense_0"], h)[:, 0])
    return np.stack(out)


def _sample(params, obs, key):
    mean, log_std = _actor(params, obs)
    eps = np.asarray(jax.random.normal(key, mean.shape, jnp.float32), np.float64)
    u = mean + np.exp(log_std) * eps
    gauss = -0.5 * eps**2 - log_std - 0.5 * np.log(2 * np.pi)
    log_prob = np.sum(gauss - np.log(1.0 - np.tanh(u) ** 2), -1)
    return np.tanh(u), log_prob


def _perturbed(params, rng, scale=0.1):
    return jax.tree.map(
        lambda x: x + jnp.asarray(scale * rng.normal(size=x.shape), x.dtype), params
    )


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(42)
    f32 = np.float32
    batch = Transition(
        obs=jnp.asarray(rng.normal(size=(B, OBS)), f32),
        action=jnp.asarray(rng.uniform(-0.9, 0.9, size=(B, ACT)), f32),
        cost=jnp.asarray(rng.uniform(size=B), f32),
        next_obs=jnp.asarray(rng.normal(size=(B, OBS)), f32),
        terminal=jnp.asarray([0.0, 0.0, 1.0, 0.0], f32),
    )
    tiny = dict(actor_hidden_sizes=(3,), critic_hidden_sizes=(3,))
    lac = make_networks(LACConfig(**tiny), ACT)
    sac = make_networks(SACConfig(**tiny), ACT)
    keys = jax.random.split(jax.random.key(42), 3)
    actor = jax.jit(lac.actor.init)(keys[0], batch.obs)
    params = {
        "actor": actor,
        "target_actor": _perturbed(actor, rng),
        "lyapunov": jax.jit(lac.critic.init)(keys[1], batch.obs, batch.action),
        "q": jax.jit(sac.critic.init)(keys[2], batch.obs, batch.action),
    }
    params["target_lyapunov"] = _perturbed(params["lyapunov"], rng)
    params["target_q"] = _perturbed(params["q"], rng)
    return batch, lac, sac, params, _np(batch)


def test_lyapunov_critic_loss_matches_numpy(setup):
    batch, lac, _, p, nb = setup
    key = jax.random.key(7)
    loss, aux = losses.lyapunov_critic_loss(
        p["lyapunov"],
        p["target_lyapunov"],
        p["target_actor"],
        batch,
        key,
        lac,
        gamma=0.9,
    )
    next_action, _ = _sample(p["target_actor"], nb.next_obs, key)
    target = nb.cost + 0.9 * (1 - nb.terminal) * _lyapunov(
        p["target_lyapunov"], nb.next_obs, next_action
    )
    value = _lyapunov(p["lyapunov"], nb.obs, nb.action)
    expected = 0.5 * np.mean((value - target) ** 2)
    np.testing.assert_allclose(float(loss), expected, rtol=1e-4)
    np.testing.assert_allclose(float(aux["lyapunov_target"]), target.mean(), rtol=1e-4)


@pytest.mark.parametrize("smoothness", [None, 0.7])
def test_lac_and_clac_actor_losses_match_numpy(setup, smoothness):
    batch, lac, _, p, nb = setup
    key = jax.random.key(3)
    weights = dict(entropy_temperature=jnp.asarray(0.5), lyapunov_multiplier=0.3)
    if smoothness is None:
        loss, aux = losses.lac_actor_loss(
            p["actor"], p["lyapunov"], batch, key, lac, alpha3=1.5, **weights
        )
    else:
        loss, aux = losses.clac_actor_loss(
            p["actor"],
            p["lyapunov"],
            batch,
            key,
            lac,
            alpha3=1.5,
            smoothness_multiplier=smoothness,
            **weights,
        )
    key_now, key_next = jax.random.split(key)
    _, log_prob = _sample(p["actor"], nb.obs, key_now)
    next_action, _ = _sample(p["actor"], nb.next_obs, key_next)
    decrease = np.mean(
        _lyapunov(p["lyapunov"], nb.next_obs, next_action)
        - _lyapunov(p["lyapunov"], nb.obs, nb.action)
        + 1.5 * nb.cost
    )
    expected = 0.5 * log_prob.mean() + 0.3 * decrease
    if smoothness is not None:
        change = np.linalg.norm(
            np.tanh(_actor(p["actor"], nb.obs)[0])
            - np.tanh(_actor(p["actor"], nb.next_obs)[0]),
            axis=-1,
        ).mean()
        expected += smoothness * change
        np.testing.assert_allclose(float(aux["action_change"]), change, rtol=1e-4)
    np.testing.assert_allclose(float(loss), expected, rtol=1e-4)
    np.testing.assert_allclose(float(aux["lyapunov_decrease"]), decrease, rtol=1e-4)
    np.testing.assert_allclose(float(aux["log_prob"]), log_prob.mean(), rtol=1e-4)


def test_soft_q_critic_loss_matches_numpy(setup):
    batch, _, sac, p, nb = setup
    key = jax.random.key(5)
    loss, _ = losses.soft_q_critic_loss(
        p["q"],
        p["target_q"],
        p["actor"],
        batch,
        key,
        sac,
        gamma=0.95,
        entropy_temperature=jnp.asarray(0.2),
    )
    next_action, next_log_prob = _sample(p["actor"], nb.next_obs, key)
    soft = _twin_q(p["target_q"], nb.next_obs, next_action).max(0) + 0.2 * next_log_prob
    target = nb.cost + 0.95 * (1 - nb.terminal) * soft
    q = _twin_q(p["q"], nb.obs, nb.action)
    expected = 0.5 * np.sum(np.mean((q - target) ** 2, axis=-1))
    np.testing.assert_allclose(float(loss), expected, rtol=1e-4)


def test_sac_actor_loss_matches_numpy(setup):
    batch, _, sac, p, nb = setup
    key = jax.random.key(9)
    loss, aux = losses.sac_actor_loss(
        p["actor"], p["q"], batch, key, sac, entropy_temperature=jnp.asarray(0.2)
    )
    action, log_prob = _sample(p["actor"], nb.obs, key)
    expected = np.mean(0.2 * log_prob + _twin_q(p["q"], nb.obs, action).max(0))
    np.testing.assert_allclose(float(loss), expected, rtol=1e-4)
    np.testing.assert_allclose(float(aux["entropy"]), -log_prob.mean(), rtol=1e-4)


def test_multiplier_losses_values_and_directions():
    log_two = jnp.log(2.0)
    # Entropy 0.5 above the target -1: the temperature must go down (gradient > 0).
    loss, aux = losses.entropy_temperature_loss(log_two, jnp.asarray(-0.5), -1.0)
    assert float(loss) == pytest.approx(1.5 * np.log(2.0))
    assert float(aux["entropy_temperature"]) == pytest.approx(2.0)
    grad = jax.grad(lambda x: losses.entropy_temperature_loss(x, -0.5, -1.0)[0])
    assert float(grad(log_two)) == pytest.approx(1.5)
    # Lyapunov condition violated (Delta = 0.3 > 0): lambda must go up.
    loss, _ = losses.lyapunov_multiplier_loss(log_two, jnp.asarray(0.3))
    assert float(loss) == pytest.approx(-0.3 * np.log(2.0))
    grad = jax.grad(lambda x: losses.lyapunov_multiplier_loss(x, 0.3)[0])
    assert float(grad(log_two)) == pytest.approx(-0.3)
    # Action change 0.01 below the 0.02 threshold: the smoothness weight goes down.
    grad = jax.grad(lambda x: losses.smoothness_multiplier_loss(x, 0.01, 0.02)[0])
    assert float(grad(log_two)) == pytest.approx(0.01)


def test_action_change_gradient_is_finite_when_actions_coincide(setup):
    # ||pi*(s) - pi*(s_near)|| as in the CLAC loss, at s_near = s
    _, lac, _, p, nb = setup
    obs = jnp.asarray(nb.obs, jnp.float32)

    def change(actor_params):
        mean, _ = lac.actor.apply(actor_params, jnp.concatenate([obs, obs]))
        squashed = deterministic_action(mean)
        return losses._safe_norm(squashed[: len(obs)] - squashed[len(obs) :]).mean()

    grads = jax.grad(change)(p["actor"])
    for leaf in jax.tree.leaves(grads):
        assert bool(jnp.all(jnp.isfinite(leaf)))
