"""Replay buffer: ring writes with wrap-around, uniform sampling of filled rows."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.agents.buffer import (
    Transition,
    add_transitions,
    init_buffer,
    sample_transitions,
)


def _batch(values):
    values = jnp.asarray(values, jnp.float32)
    n = values.shape[0]
    return Transition(
        obs=jnp.tile(values[:, None], (1, 3)),
        action=jnp.tile(values[:, None], (1, 2)),
        cost=values,
        next_obs=jnp.tile(values[:, None] + 0.5, (1, 3)),
        terminal=jnp.zeros((n,)),
    )


@pytest.mark.parametrize("transform", [lambda f: f, jax.jit])
def test_add_wraps_around_and_overwrites_oldest(transform):
    add = transform(add_transitions)
    buffer = init_buffer(5, 3, 2)
    buffer = add(buffer, _batch([1, 2, 3]))
    assert int(buffer.position) == 3 and int(buffer.size) == 3
    buffer = add(buffer, _batch([4, 5, 6]))
    assert int(buffer.position) == 1 and int(buffer.size) == 5
    np.testing.assert_array_equal(buffer.data.cost, [6, 2, 3, 4, 5])
    np.testing.assert_array_equal(buffer.data.next_obs[0], [6.5] * 3)
    buffer = add(buffer, _batch([7, 8, 9, 10, 11]))
    assert int(buffer.position) == 1 and int(buffer.size) == 5
    np.testing.assert_array_equal(buffer.data.cost, [11, 7, 8, 9, 10])


def test_sample_draws_only_filled_rows():
    buffer = add_transitions(init_buffer(10, 3, 2), _batch([1, 2, 3]))
    batch = jax.jit(sample_transitions, static_argnums=2)(
        jax.random.key(0), buffer, 300
    )
    assert batch.obs.shape == (300, 3) and batch.action.shape == (300, 2)
    assert set(np.asarray(batch.cost).tolist()) == {1.0, 2.0, 3.0}
    # Rows stay consistent across fields.
    np.testing.assert_array_equal(batch.obs[:, 0], batch.cost)
    np.testing.assert_array_equal(batch.next_obs[:, 0], batch.cost + 0.5)


def test_add_rejects_batch_larger_than_capacity():
    with pytest.raises(ValueError, match="capacity"):
        add_transitions(init_buffer(2, 3, 2), _batch([1, 2, 3]))


def test_init_rejects_non_positive_sizes():
    with pytest.raises(ValueError, match="capacity"):
        init_buffer(0, 3, 2)
