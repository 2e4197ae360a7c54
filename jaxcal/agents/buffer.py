"""Replay buffer on device: preallocated arrays, a write position and a size.

The buffer is a ring: :func:`add_transitions` writes a batch of ``B`` transitions
at ``position, ..., position + B - 1`` modulo the capacity, overwriting the oldest
ones when full; :func:`sample_transitions` draws uniformly among the ``size`` filled
rows. All functions are pure and jittable; the capacity is the (static) leading
dimension of the arrays.

CLAC needs a state "near" s (paper eq. CLAC: "we use the adjacent time space state
s_{t+1} to approximate s_near"): that is the ``next_obs`` of the same transition, which
is stored anyway, so no extra field is needed.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from jaxcal.typedefs import Array, PRNGKey


class Transition(NamedTuple):
    """One (or a batch of) MDP transition(s) (s, a, c, s', terminal).

    Attributes:
        obs: s_t, ``[..., O]``.
        action: a_t in [-1, 1]^A (squashed), ``[..., A]``.
        cost: c_t, ``[...]``.
        next_obs: s_{t+1} (also the CLAC near state), ``[..., O]``.
        terminal: 1.0 where s_{t+1} is terminal, i.e. the bootstrap is cut. The end of a
            tracking window is a time limit, not a terminal state, so the tracking
            environment always stores 0 here.
    """

    obs: Array
    action: Array
    cost: Array
    next_obs: Array
    terminal: Array


@struct.dataclass
class ReplayBuffer:
    """Ring buffer of transitions.

    Attributes:
        data: a :class:`Transition` of arrays with leading dimension ``capacity``.
        position: [] int32, next row to write.
        size: [] int32, number of filled rows (<= capacity).
    """

    data: Transition
    position: Array
    size: Array

    @property
    def capacity(self) -> int:
        """Number of rows (static)."""
        return self.data.cost.shape[0]


def init_buffer(capacity: int, obs_size: int, action_size: int) -> ReplayBuffer:
    """Allocates an empty float32 buffer.

    Args:
        capacity: number of transitions it holds.
        obs_size: O.
        action_size: A.

    Returns:
        A :class:`ReplayBuffer` with zero-filled arrays and ``size == 0``.
    """
    for name, value in (
        ("capacity", capacity),
        ("obs_size", obs_size),
        ("action_size", action_size),
    ):
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    f32 = jnp.float32
    data = Transition(
        obs=jnp.zeros((capacity, obs_size), f32),
        action=jnp.zeros((capacity, action_size), f32),
        cost=jnp.zeros((capacity,), f32),
        next_obs=jnp.zeros((capacity, obs_size), f32),
        terminal=jnp.zeros((capacity,), f32),
    )
    # Separate zero arrays: one shared buffer could not be donated to jit twice.
    return ReplayBuffer(
        data=data, position=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32)
    )


def add_transitions(buffer: ReplayBuffer, batch: Transition) -> ReplayBuffer:
    """Writes a batch of ``B`` transitions (leading axis ``B <= capacity``).

    Args:
        buffer: the current buffer.
        batch: a :class:`Transition` whose leaves have a leading ``[B]`` axis.

    Returns:
        The buffer with the batch written at the ring position.
    """
    num_new = batch.cost.shape[0]
    if num_new > buffer.capacity:
        raise ValueError(
            f"batch of {num_new} transitions exceeds the buffer capacity "
            f"{buffer.capacity}"
        )
    rows = (buffer.position + jnp.arange(num_new, dtype=jnp.int32)) % buffer.capacity
    data = jax.tree.map(
        lambda store, new: store.at[rows].set(new.astype(store.dtype)),
        buffer.data,
        batch,
    )
    return ReplayBuffer(
        data=data,
        position=(buffer.position + num_new) % buffer.capacity,
        size=jnp.minimum(buffer.size + num_new, buffer.capacity),
    )


def sample_transitions(
    key: PRNGKey, buffer: ReplayBuffer, batch_size: int
) -> Transition:
    """Draws ``batch_size`` transitions uniformly, with replacement, from filled rows.

    Sampling an empty buffer returns row 0 (zeros); callers gate updates on ``size``.

    Args:
        key: PRNG key.
        buffer: the buffer.
        batch_size: number of rows.

    Returns:
        A :class:`Transition` with leading axis ``[batch_size]``.
    """
    rows = jax.random.randint(
        key, (batch_size,), 0, jnp.maximum(buffer.size, 1), dtype=jnp.int32
    )
    return jax.tree.map(lambda store: store[rows], buffer.data)
