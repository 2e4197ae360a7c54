"""A pytree packed into per-dtype buffers comes back exactly, and the guard's select
on packed leaves keeps or replaces every leaf as a select per leaf would."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.guard import keep_where
from jaxcal.calibrators.programs.packed import Packing, jit_per_row


def _tree(shift):
    return {
        "a": jnp.arange(6.0, dtype=jnp.float32).reshape(2, 3) + shift,
        "b": (
            jnp.int32(3 + shift),
            jnp.ones((), bool) if shift else jnp.zeros((), bool),
        ),
        "c": None,
        "d": jnp.float32(shift),
        "key": jax.random.key(shift),
    }


def test_pack_round_trip_keeps_values_and_dtypes():
    tree = _tree(1)
    packing = Packing.of(tree)
    buffers = jax.jit(packing.pack)(tree)
    assert len(buffers) == 4  # float, int, bool, the key on its own
    back = jax.jit(packing.unpack)(buffers)
    for got, want in zip(jax.tree.leaves(back), jax.tree.leaves(tree), strict=True):
        assert got.dtype == want.dtype and got.shape == want.shape
    np.testing.assert_array_equal(back["a"], tree["a"])
    assert int(back["b"][0]) == 4 and bool(back["b"][1])
    assert back["c"] is None
    np.testing.assert_array_equal(
        jax.random.key_data(back["key"]), jax.random.key_data(tree["key"])
    )


def test_a_large_leaf_keeps_a_buffer_of_its_own():
    tree = {
        "a": jnp.arange(3.0, dtype=jnp.float32),
        "big": jnp.arange(12.0, dtype=jnp.float32).reshape(3, 4),
        "c": jnp.float32(7.0),
        "n": jnp.arange(5, dtype=jnp.int32),
    }
    packing = Packing.of(tree, alone_from=6)
    buffers = jax.jit(packing.pack)(tree)
    # the small floats share one buffer, the large one has its own, the ints another
    assert sorted(b.shape for b in buffers) == [(3, 4), (4,), (5,)]
    back = jax.jit(packing.unpack)(buffers)
    for got, want in zip(jax.tree.leaves(back), jax.tree.leaves(tree), strict=True):
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)


def test_keep_where_selects_whole_trees():
    new, old = _tree(1), _tree(0)
    for ok, want in ((True, new), (False, old)):
        got = jax.jit(keep_where)(jnp.asarray(ok), new, old)
        np.testing.assert_array_equal(got["a"], want["a"])
        np.testing.assert_array_equal(got["d"], want["d"])
        assert int(got["b"][0]) == int(want["b"][0])
        assert bool(got["b"][1]) == bool(want["b"][1])


def test_a_per_row_program_computes_the_bits_of_the_default_one():
    # a small filter-like step: independent dots, reductions and a guard, the kind
    # of program whose kernels the per-row schedule orders differently
    def step(carry, row):
        p, theta = carry
        h = jnp.tanh(weights @ row + p @ theta)
        gain = p @ h[:3] / (1.0 + jnp.sum(h * h))
        new = (p - jnp.outer(gain, gain) * 0.1, theta + gain)
        ok = jnp.all(jnp.isfinite(row))
        return jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, carry), gain

    rng = np.random.default_rng(0)
    weights = jnp.asarray(rng.normal(size=(3, 5)), jnp.float32)
    rows = rng.normal(size=(20, 5)).astype(np.float32)
    rows[4, 1], rows[9] = np.nan, np.inf  # skipped rows
    carry0 = (jnp.eye(3, dtype=jnp.float32), jnp.zeros(3, jnp.float32))
    outs = []
    for jit in (jax.jit, jit_per_row):
        carry, got = carry0, []
        fn = jit(step)
        for row in rows:
            carry, gain = fn(carry, row)
            got.append(np.asarray(gain))
        outs.append((np.stack(got), np.asarray(carry[0]), np.asarray(carry[1])))
    for default, per_row in zip(*outs, strict=True):
        assert np.array_equal(default.view(np.uint32), per_row.view(np.uint32))
