"""Tests for the end-to-end baseline G: features, fitting, prediction, calibrator."""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.e2e_batch import e2e_predict

from jaxcal.calibrators.interface import run_fleet
from jaxcal.calibrators.methods.e2e.network import (
    E2EConfig,
    e2e_features,
    fit_e2e,
    init_e2e_params,
    make_e2e_calibrator,
)
from jaxcal.nets.mlp import RegressorConfig

TINY = E2EConfig(
    hidden_sizes=(64,),
    fit=RegressorConfig(learning_rate=1e-2, batch_size=32, num_epochs=40),
)


def toy_model(w, theta):
    """Invertible given w: θ0 = (x0 − w0) / 2, θ1 = x2 − w0 / 2 − 0.3·θ0²."""
    return jnp.stack(
        [
            w[..., 0] + 2.0 * theta[..., 0],
            jnp.tanh(w[..., 1]) - theta[..., 1] + 0.5 * theta[..., 0],
            0.5 * w[..., 0] + theta[..., 1] + 0.3 * theta[..., 0] ** 2,
        ],
        axis=-1,
    )


def toy_fleet(seed, num_units=16, num_steps=48):
    """Units with degrading θ, random conditions and trailing padding."""
    rng = np.random.default_rng(seed)
    w = rng.uniform(-1.0, 1.0, (num_units, num_steps, 2))
    start = rng.uniform(-1.0, 1.0, (num_units, 1, 2))
    theta = start - 0.01 * np.arange(num_steps)[None, :, None]
    x = np.asarray(toy_model(w, theta))
    lengths = num_steps - 5 * (np.arange(num_units) % 4)
    mask = np.arange(num_steps)[None, :] < lengths[:, None]
    return w, x, theta, mask


def test_features_use_x_t_where_previous_sample_is_missing():
    x = np.arange(8.0).reshape(1, 4, 2)
    w = np.zeros((1, 4, 1))
    feats = e2e_features(w, x)
    np.testing.assert_array_equal(feats[0, :, 3:], [[0, 1], [0, 1], [2, 3], [4, 5]])
    # With leading padding, the first valid sample (t = 2) pairs with itself.
    mask = np.array([[False, False, True, True]])
    feats = e2e_features(w, x, mask)
    np.testing.assert_array_equal(feats[0, 2:, 3:], [[4, 5], [4, 5]])


def test_e2e_learns_theta_from_an_invertible_model():
    w, x, theta, mask = toy_fleet(0)
    params, history = fit_e2e(jax.random.key(0), w, x, theta, mask, TINY)
    assert history["train_loss"][-1] < 0.02 * history["train_loss"][0]
    w_t, x_t, theta_t, mask_t = toy_fleet(1, num_units=3)
    pred = jax.jit(e2e_predict)(params, w_t, x_t, mask_t)
    chex.assert_shape(pred, theta_t.shape)
    err = np.where(mask_t[..., None], np.asarray(pred) - theta_t, 0.0)
    rmse = np.sqrt((err**2).sum(axis=(0, 1)) / mask_t.sum())
    # Held-out units; predicting the mean would give about 1 on this scale.
    assert np.all(rmse < 0.08 * theta_t[mask_t].std(axis=0)), rmse


def test_calibrator_streams_the_same_answer_as_batch_prediction():
    cfg = dataclasses.replace(TINY, hidden_sizes=(8,))
    params = init_e2e_params(jax.random.key(0), 2, 3, 2, cfg)
    w, x, _, mask = toy_fleet(2, num_units=2, num_steps=9)
    batch = e2e_predict(params, w, x, mask)
    calibrator = make_e2e_calibrator(params, measure=toy_model)
    out = jax.jit(lambda w, x, m: run_fleet(calibrator, w, x, m))(w, x, mask)
    valid = mask[..., None]
    np.testing.assert_allclose(
        np.where(valid, out.theta, 0.0),
        np.where(valid, batch, 0.0),
        rtol=1e-5,
        atol=1e-6,
    )
    np.testing.assert_allclose(
        np.where(valid, out.xhat, 0.0),
        np.where(valid, toy_model(w, out.theta), 0.0),
        rtol=1e-6,
    )
    # Without a model the output has no model prediction: NaN, not a fake x_t.
    bare = make_e2e_calibrator(params)
    state, step_out = bare.step(bare.init(None, w[0, 0], x[0, 0]), w[0, 1], x[0, 1])
    assert np.isnan(np.asarray(step_out.xhat)).all()
    np.testing.assert_allclose(step_out.theta, batch[0, 1], rtol=1e-5)
    np.testing.assert_array_equal(state.x_prev, x[0, 1])


def test_fit_e2e_rejects_inconsistent_shapes():
    w, x, theta, mask = toy_fleet(3, num_units=2, num_steps=8)
    with pytest.raises(ValueError, match="theta must be"):
        fit_e2e(jax.random.key(0), w, x, theta[:, :5], mask, TINY)
