"""Tests for the shared MLP and the jitted regression trainer."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.nets.mlp import (
    MLP,
    RegressorConfig,
    fit_normalizer,
    fit_regressor,
    regressor_apply,
)


def smooth_data(seed, n=512):
    """A smooth 2-D -> 2-D map with features on very different scales."""
    u = np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 2))
    inputs = np.stack([u[:, 0] * 1000.0 + 5000.0, u[:, 1]], axis=1)
    targets = np.stack(
        [np.sin(2.0 * u[:, 0]) + 0.5 * u[:, 1] ** 2, 300.0 + 20.0 * u[:, 0] * u[:, 1]],
        axis=1,
    )
    return inputs, targets


def test_mlp_is_float32_with_glorot_kernels_under_x64():
    model = MLP(hidden_sizes=(8, 8), output_dim=3)
    x = jnp.ones((4, 5), dtype=jnp.float64)
    params = model.init(jax.random.key(0), x)["params"]
    assert set(params) == {"hidden_0", "hidden_1", "output"}
    out = model.apply({"params": params}, x)
    chex.assert_shape(out, (4, 3))
    assert out.dtype == jnp.float32
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(params))
    # Glorot uniform: |w| <= sqrt(6 / (fan_in + fan_out)); biases start at zero.
    assert jnp.abs(params["hidden_0"]["kernel"]).max() <= np.sqrt(6 / 13)
    assert jnp.all(params["hidden_0"]["bias"] == 0)
    with pytest.raises(ValueError, match="activation must be one of"):
        MLP((4,), 1, activation="swish2").init(jax.random.key(0), x)


def test_normalizer_keeps_constant_features_finite():
    values = np.array([[1.0, 7.0], [3.0, 7.0], [5.0, 7.0]])
    norm = fit_normalizer(values)
    z = norm.normalize(jnp.asarray(values))
    assert jnp.all(jnp.isfinite(z))
    np.testing.assert_allclose(norm.std, [np.std([1.0, 3.0, 5.0]), 1.0], rtol=1e-6)
    np.testing.assert_allclose(norm.denormalize(z), values, rtol=1e-6)


def test_regressor_fits_a_smooth_2d_function():
    inputs, targets = smooth_data(1)
    cfg = RegressorConfig(learning_rate=5e-3, batch_size=64, num_epochs=50)
    model = MLP(hidden_sizes=(64, 64), output_dim=2)
    logged = []
    params, history = fit_regressor(
        jax.random.key(2),
        model,
        inputs,
        targets,
        cfg,
        log_fn=lambda e, r: logged.append(e),
    )
    assert history["epochs_run"] == 50 and logged == list(range(50))  # 400 SGD steps
    assert history["train_loss"][-1] < 0.01 * history["train_loss"][0]
    test_in, test_out = smooth_data(3, n=256)
    pred = jax.jit(lambda p, x: regressor_apply(model, p, x))(params, test_in)
    # Held-out RMSE per output, relative to that output's spread (≈ 0.6 and ≈ 6.7).
    rel_rmse = jnp.sqrt(jnp.mean((pred - test_out) ** 2, axis=0)) / test_out.std(0)
    assert jnp.all(rel_rmse < 0.05), rel_rmse


def test_validation_split_and_early_stopping_return_best_epoch():
    inputs, targets = smooth_data(4, n=200)
    # Pure noise targets: validation loss cannot improve for long, so training stops.
    noise = np.random.default_rng(5).normal(size=targets.shape)
    cfg = RegressorConfig(
        learning_rate=1e-2,
        batch_size=32,
        num_epochs=200,
        validation_fraction=0.25,
        patience=3,
    )
    model = MLP(hidden_sizes=(16,), output_dim=2)
    params, history = fit_regressor(jax.random.key(6), model, inputs, noise, cfg)
    assert history["stopped_early"] and history["epochs_run"] < 200
    assert history["epochs_run"] == history["best_epoch"] + 1 + cfg.patience
    assert len(history["val_loss"]) == history["epochs_run"]
    assert history["val_loss"].argmin() == history["best_epoch"]


def test_bad_data_and_config_raise_value_errors():
    model = MLP(hidden_sizes=(4,), output_dim=1)
    cfg = RegressorConfig(num_epochs=1)
    x = np.ones((10, 2))
    with pytest.raises(ValueError, match="same N"):
        fit_regressor(jax.random.key(0), model, x, np.ones((9, 1)), cfg)
    x_nan = x.copy()
    x_nan[3, 1] = np.nan
    with pytest.raises(ValueError, match="inputs contain NaN or inf \\(first at row 3"):
        fit_regressor(jax.random.key(0), model, x_nan, np.ones((10, 1)), cfg)
    with pytest.raises(ValueError, match="validation_fraction"):
        RegressorConfig(validation_fraction=1.0)
    with pytest.raises(ValueError, match="needs validation_fraction"):
        RegressorConfig(patience=5)
