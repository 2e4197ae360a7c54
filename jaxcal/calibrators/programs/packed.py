"""What a program called once per row (a stream's step) needs to be cheap on XLA's
CPU runtime: its carry packed into one flat buffer per dtype, and its compile options.

A stream's carry (the policy's state, the guard's last outputs and rows) has a dozen
or more small leaves. Passed as they are, every sample pays for each leaf three times
on XLA's CPU runtime: parsing it as an argument, selecting it in the guard (one
kernel per leaf) and allocating it as an output. Packed into one buffer per dtype
(float, int, bool: at most a few), the leaves become slices of an argument, which
fuse into their consumers, and a select of the whole carry (the guard's) is one kernel
per dtype. Values are unchanged (no dtype is converted); a leaf of an extended dtype
(a typed PRNG key) keeps a buffer of its own.

:func:`jit_per_row` compiles such a program with :data:`PER_ROW_OPTIONS`, per program
(never as a process-wide flag): XLA's CPU runtime runs a program as a graph of
kernels, starts every kernel whose inputs are ready, and hands part of a wide ready
set to its thread pool. A stream's step is ~100 kernels of a few hundred flops each,
and a hand-off to another thread costs more than the kernels it carries. XLA's
default schedule keeps independent kernels apart for concurrency; the
memory-optimised schedule reuses buffers, which orders the kernels into fewer ready
at a time: a faster call, the same bits (``results/bench/stream_profile.md``). Not
for a model that carries a warm-started solve from row to row (the turbofan's
Broyden, ``Model.evaluate_hinted``): there the schedule changes the solve's numbers
and gains nothing, so such a program keeps XLA's defaults (``warm_solve``).

:func:`synchronous_dispatch` goes one step further, for the whole process: JAX's CPU
client hands every call to a thread of its own and the caller waits for it, which on
a step of ~100 small kernels costs as much as the kernels
(``results/bench/stream_profile.md``). JAX reads that setting once, when its
CPU backend starts, so it is an entry point's call (as ``enable_x64``), never a
library's.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax._src import xla_bridge

from jaxcal.typedefs import Array

# compile options of a program called once per row (module docstring)
PER_ROW_OPTIONS = {"xla_cpu_scheduler_type": "CPU_SCHEDULER_TYPE_MEMORY_OPTIMIZED"}


# JAX's setting (its environment variable: JAX_CPU_ENABLE_ASYNC_DISPATCH)
DISPATCH_FLAG = "jax_cpu_enable_async_dispatch"


def synchronous_dispatch() -> None:
    """Run JAX's CPU calls on the calling thread, for the lowest cost a row
    (module docstring). Call it at the start of the program, before any JAX
    computation, or set ``JAX_CPU_ENABLE_ASYNC_DISPATCH=false`` in the environment.
    Only single-device calls change; their results are the same bits.

    Raises:
        RuntimeError: JAX's backend has already started with asynchronous dispatch
            (the setting would be ignored without a word).
    """
    if dispatch_is_synchronous():
        return
    # JAX has no public test of a started backend; without it the flag is still set
    started = getattr(xla_bridge, "backends_are_initialized", lambda: False)()
    if started:
        raise RuntimeError(
            "synchronous_dispatch() must run before JAX's first computation (its CPU "
            "backend has started, with asynchronous dispatch): call it at the start "
            "of the program, or set JAX_CPU_ENABLE_ASYNC_DISPATCH=false in the "
            "environment"
        )
    jax.config.update(DISPATCH_FLAG, False)


def dispatch_is_synchronous() -> bool:
    """True when JAX runs CPU calls on the calling thread
    (:func:`synchronous_dispatch`)."""
    return not jax.config.values[DISPATCH_FLAG]


def jit_per_row(fn, *, warm_solve: bool = False, **jit_kwargs):
    """``jax.jit(fn)`` compiled with :data:`PER_ROW_OPTIONS`: for a stream's step,
    called once per row with few, small arrays. ``warm_solve``: the step carries a
    model's warm-started solve (module docstring): XLA's defaults."""
    options = None if warm_solve else PER_ROW_OPTIONS
    return jax.jit(fn, compiler_options=options, **jit_kwargs)


@dataclasses.dataclass(frozen=True)
class Packing:
    """Where each leaf of a pytree lives in the per-dtype buffers."""

    treedef: jax.tree_util.PyTreeDef
    # each buffer's dtype: one shared buffer per dtype in first-seen order, and one
    # per leaf kept alone (an extended dtype's, or a large one: ``of``'s alone_from)
    dtypes: tuple[np.dtype, ...]
    # per leaf: (buffer, start, size, shape); start -1: the leaf is its buffer
    slots: tuple[tuple[int, int, int, tuple[int, ...]], ...]

    @classmethod
    def of(cls, tree, alone_from: int | None = None) -> Packing:
        """The packing of trees shaped as ``tree`` (its leaves' shapes and dtypes).

        ``alone_from``: a leaf of at least this many elements keeps a buffer of its
        own. A slice of a buffer that a dot reads is copied at every call (the
        turbofan actor's 256 x 256 weights: 256 KB, split over two threads), an
        argument costs about as much as one small kernel."""
        leaves, treedef = jax.tree.flatten(tree)
        dtypes: list[np.dtype] = []
        sizes: list[int] = []
        shared: dict[np.dtype, int] = {}  # the buffer each plain dtype's leaves share
        slots = []
        for leaf in leaves:
            dtype, shape = leaf.dtype, tuple(np.shape(leaf))
            size = math.prod(shape)
            if jax.dtypes.issubdtype(dtype, jax.dtypes.extended) or (
                alone_from is not None and size >= alone_from
            ):
                slots.append((len(dtypes), -1, 0, shape))
                dtypes.append(dtype)
                sizes.append(0)
                continue
            dtype = np.dtype(dtype)
            if dtype not in shared:
                shared[dtype] = len(dtypes)
                dtypes.append(dtype)
                sizes.append(0)
            k = shared[dtype]
            slots.append((k, sizes[k], size, shape))
            sizes[k] += size
        return cls(treedef, tuple(dtypes), tuple(slots))

    def pack(self, tree) -> tuple[Array, ...]:
        """The buffers holding ``tree``'s leaves (jittable)."""
        leaves = self.treedef.flatten_up_to(tree)
        parts: list[list[Array]] = [[] for _ in self.dtypes]
        for leaf, (k, start, _, _) in zip(leaves, self.slots, strict=True):
            parts[k].append(
                leaf if start < 0 else jnp.ravel(jnp.asarray(leaf, self.dtypes[k]))
            )
        return tuple(p[0] if len(p) == 1 else jnp.concatenate(p) for p in parts)

    def unpack(self, buffers: tuple[Array, ...]):
        """The tree the buffers hold (jittable)."""
        leaves = [
            buffers[k] if start < 0 else buffers[k][start : start + size].reshape(shape)
            for k, start, size, shape in self.slots
        ]
        return self.treedef.unflatten(leaves)
