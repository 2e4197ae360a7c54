"""Tests for the surrogate D: transition building, fitting, errors, env signature."""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.nets.mlp import RegressorConfig
from jaxcal.runs.checkpoint import Checkpointer
from jaxcal.surrogate.fit import (
    fit_surrogate,
    make_transitions,
    surrogate_errors,
)
from jaxcal.surrogate.model import (
    SurrogateConfig,
    init_surrogate_params,
    surrogate_apply,
)

TINY = SurrogateConfig(
    hidden_sizes=(32,),
    fit=RegressorConfig(learning_rate=1e-2, batch_size=32, num_epochs=60),
)


def linear_fleet(seed, num_units=8, num_steps=64):
    """x_{t+1} = A x_t + B w_{t+1} + C θ_{t+1}, stable A, units of unequal length."""
    rng = np.random.default_rng(seed)
    a = np.array([[0.5, 0.1, 0.0], [0.0, 0.4, 0.1], [0.1, 0.0, 0.3]])
    b = np.array([[1.0, 0.0], [0.5, -1.0], [0.0, 2.0]])
    c = np.array([[2.0], [0.0], [-1.0]])
    w = rng.uniform(-1.0, 1.0, (num_units, num_steps, 2))
    theta0 = rng.uniform(0.0, 0.5, (num_units, 1, 1))
    theta = theta0 - 0.01 * np.arange(num_steps)[None, :, None]
    x = np.zeros((num_units, num_steps, 3))
    x[:, 0] = rng.normal(size=(num_units, 3))
    for t in range(num_steps - 1):
        x[:, t + 1] = x[:, t] @ a.T + w[:, t + 1] @ b.T + theta[:, t + 1] @ c.T
    lengths = num_steps - 4 * np.arange(num_units)
    mask = np.arange(num_steps)[None, :] < lengths[:, None]
    # Padding holds garbage, as a loader might leave it.
    for v in (w, x, theta):
        v[~mask] = np.nan
    return w, x, theta, mask


def test_make_transitions_respects_the_mask():
    w = np.arange(2 * 4 * 1, dtype=float).reshape(2, 4, 1)
    x = 10 + w.repeat(2, axis=-1)
    theta = -w
    mask = np.array([[True, True, True, True], [True, True, False, False]])
    tr = make_transitions(w, x, theta, mask)
    # Unit 0 gives 3 pairs, unit 1 only (t=0 -> 1); nothing crosses the padding.
    np.testing.assert_array_equal(tr.w_next[:, 0], [1, 2, 3, 5])
    np.testing.assert_array_equal(tr.theta_next[:, 0], [-1, -2, -3, -5])
    np.testing.assert_array_equal(tr.x[:, 0], [10, 11, 12, 14])
    np.testing.assert_array_equal(tr.x_next[:, 1], [11, 12, 13, 15])
    with pytest.raises(ValueError, match="no pair"):
        make_transitions(w, x, theta, np.eye(2, 4, dtype=bool))
    with pytest.raises(ValueError, match="theta must be \\[U, T, ·\\]"):
        make_transitions(w, x, theta[:, :3], mask)


def test_surrogate_learns_a_linear_dynamical_system():
    w, x, theta, mask = linear_fleet(0)
    transitions = make_transitions(w, x, theta, mask)
    assert len(transitions.x) == int((mask[:, :-1] & mask[:, 1:]).sum())
    assert np.isfinite(transitions.x_next).all()
    params, history = fit_surrogate(jax.random.key(1), transitions, TINY)
    assert history["train_loss"][-1] < 0.02 * history["train_loss"][0]
    # Fresh trajectories of the same system.
    errors = surrogate_errors(params, *linear_fleet(2, num_units=3))
    for name in ("one_step", "free_run"):
        chex.assert_shape(errors[f"{name}_rmse"], (3,))
        chex.assert_tree_all_finite(errors[f"{name}_rmse"])
    assert errors["num_pairs"] == 63 + 59 + 55
    assert errors["one_step_rmse_norm_mean"] < 0.05, errors
    # Fed back its own output, D drifts more, but the stable system keeps it bounded.
    assert errors["one_step_rmse_norm_mean"] <= errors["free_run_rmse_norm_mean"] < 0.1
    np.testing.assert_allclose(
        errors["one_step_rmse_norm"],
        errors["one_step_rmse"] / params.regressor.target_norm.std,
        rtol=1e-6,
    )


def test_surrogate_apply_is_the_env_dynamics_signature():
    cfg = dataclasses.replace(TINY, hidden_sizes=(8,))
    params = init_surrogate_params(jax.random.key(0), 2, 3, 1, cfg)
    w_next = jnp.ones((5, 2))
    xhat = jnp.zeros((5, 3), jnp.float64)
    theta = jnp.array([0.1])  # one θ broadcast over the batch

    @jax.jit
    def dynamics(dyn_params, w_next, xhat, theta):
        return surrogate_apply(dyn_params, w_next, xhat, theta)

    out = dynamics(params, w_next, xhat, theta)
    chex.assert_shape(out, (5, 3))
    assert out.dtype == xhat.dtype  # scan carries keep their dtype
    np.testing.assert_allclose(
        out[0], dynamics(params, w_next[0], xhat[0], theta), rtol=1e-6
    )
    # Usable as a restore target: static shape survives eval_shape.
    abstract = jax.eval_shape(
        lambda k: init_surrogate_params(k, 2, 3, 1, cfg), jax.random.key(0)
    )
    assert abstract.sensor_dim == 3
    with pytest.raises(ValueError, match="xhat must have last dimension 3"):
        surrogate_apply(params, w_next, jnp.zeros((5, 4)), theta)


def test_surrogate_compiles_once_and_survives_a_checkpoint(tmp_path):
    cfg = dataclasses.replace(TINY, hidden_sizes=(8,))
    params = init_surrogate_params(jax.random.key(0), 2, 3, 1, cfg)
    other = init_surrogate_params(jax.random.key(1), 2, 3, 1, cfg)
    chex.clear_trace_counter()
    dynamics = jax.jit(chex.assert_max_traces(surrogate_apply, n=1))
    args = (jnp.ones((4, 2)), jnp.zeros((4, 3)), jnp.ones((4, 1)))
    first, second = dynamics(params, *args), dynamics(other, *args)
    assert not jnp.allclose(first, second)  # new weights, same compiled function
    with Checkpointer(tmp_path) as ckpt:
        ckpt.save(0, other, wait=True)
        abstract = jax.eval_shape(
            lambda k: init_surrogate_params(k, 2, 3, 1, cfg), jax.random.key(0)
        )
        restored = ckpt.restore(0, abstract)
    chex.assert_trees_all_equal(restored, other)
    np.testing.assert_array_equal(dynamics(restored, *args), second)
