"""Tests for the Orbax checkpoint wrapper and the config JSON side file."""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import optax
import pytest
from flax import struct

from jaxcal.runs.checkpoint import Checkpointer, load_config, save_config


@struct.dataclass
class TinyState:
    params: dict
    opt_state: optax.OptState
    key: jax.Array
    step: jax.Array


def init_state(key: jax.Array) -> TinyState:
    key_w, key_run = jax.random.split(key)
    params = {
        "encoder": {"kernel": jax.random.normal(key_w, (3, 4)), "bias": jnp.zeros(4)},
        "head": {"kernel": jnp.ones((4, 2), jnp.float32)},
    }
    return TinyState(
        params=params,
        opt_state=optax.adam(1e-3).init(params),
        key=key_run,
        step=jnp.array(0, jnp.int32),
    )


def advanced_state() -> TinyState:
    """A state whose optimiser moments and key differ from a fresh init."""
    state = init_state(jax.random.key(7))
    opt = optax.adam(1e-3)
    grads = jax.tree.map(jnp.ones_like, state.params)
    updates, opt_state = opt.update(grads, state.opt_state, state.params)
    return state.replace(
        params=optax.apply_updates(state.params, updates),
        opt_state=opt_state,
        key=jax.random.split(state.key)[0],
        step=state.step + 5,
    )


def test_save_restore_round_trip_with_typed_key_and_optax_state(tmp_path):
    state = advanced_state()
    with Checkpointer(tmp_path / "ckpt", max_to_keep=2) as ckpt:
        ckpt.save(5, state)
        ckpt.wait_until_finished()
        assert ckpt.latest_step() == 5
    # A fresh manager (as in a new process) restores into an abstract target.
    with Checkpointer(tmp_path / "ckpt") as ckpt:
        abstract = jax.eval_shape(init_state, jax.random.key(0))
        restored = ckpt.restore(None, abstract)
    assert isinstance(restored, TinyState)
    assert jax.dtypes.issubdtype(restored.key.dtype, jax.dtypes.prng_key)
    assert jax.random.key_impl(restored.key) == jax.random.key_impl(state.key)
    chex.assert_trees_all_equal(
        jax.random.key_data(restored.key), jax.random.key_data(state.key)
    )
    chex.assert_trees_all_equal(restored.replace(key=None), state.replace(key=None))
    # The restored key draws the same numbers as the original one.
    assert jnp.array_equal(
        jax.random.uniform(restored.key, (3,)), jax.random.uniform(state.key, (3,))
    )


def test_max_to_keep_and_duplicate_step(tmp_path):
    state = init_state(jax.random.key(0))
    with Checkpointer(tmp_path, max_to_keep=2) as ckpt:
        for step in (1, 2, 3):
            ckpt.save(step, state.replace(step=jnp.array(step, jnp.int32)), wait=True)
        assert ckpt.all_steps() == [2, 3]
        with pytest.raises(ValueError, match="already exists"):
            ckpt.save(3, state)
        restored = ckpt.restore(2, jax.eval_shape(init_state, jax.random.key(0)))
        assert int(restored.step) == 2
        with pytest.raises(FileNotFoundError, match="saved: \\[2, 3\\]"):
            ckpt.restore(1, state)


def test_restore_with_wrong_structure_or_shape_fails_loudly(tmp_path):
    state = init_state(jax.random.key(0))
    with Checkpointer(tmp_path) as ckpt:
        ckpt.save(1, state, wait=True)
        extra = state.replace(params={**state.params, "extra": jnp.zeros(2)})
        with pytest.raises(ValueError, match="missing in checkpoint.*params/extra"):
            ckpt.restore(1, jax.eval_shape(lambda: extra))
        wider = state.replace(
            params={**state.params, "head": {"kernel": jnp.ones((4, 3))}}
        )
        with pytest.raises(ValueError, match="params/head/kernel: stored \\(4, 2\\)"):
            ckpt.restore(1, jax.eval_shape(lambda: wider))
        fewer = state.replace(opt_state=optax.sgd(1e-3).init(state.params))
        with pytest.raises(ValueError, match="not in target.*opt_state"):
            ckpt.restore(1, jax.eval_shape(lambda: fewer))


@dataclasses.dataclass(frozen=True)
class RunConfig:
    seed: int = 0
    lr: float = 1e-3
    theta: tuple[str, ...] = ("HPT_eff_mod",)


def test_config_json_is_written_atomically_and_round_trips(tmp_path):
    cfg = RunConfig(seed=3, theta=("a", "b"))
    path = save_config(tmp_path / "run", cfg)
    assert path.name == "config.json"
    assert sorted(p.name for p in path.parent.iterdir()) == ["config.json"]
    assert load_config(tmp_path / "run", RunConfig) == cfg
    assert load_config(tmp_path / "run")["theta"] == ["a", "b"]
    with pytest.raises(FileNotFoundError):
        load_config(tmp_path / "missing")
