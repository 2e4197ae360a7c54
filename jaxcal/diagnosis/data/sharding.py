"""The diagnosis's model evaluations split over the processes of a JAX cluster.

A diagnosis on several ``jax.distributed`` processes (``python -m jaxcal.diagnose
--num-processes 2 ...``, :func:`jaxcal.fleet.distributed.initialize`) is
multi-controller: every process runs the same diagnosis on the same rows, and only
its hot part, the model's evaluation, is divided. Each process evaluates its own
contiguous block of the items (a static model's row chunks, rows ordered by unit:
a block of units; a model with memory's units), the blocks are exchanged with
``process_allgather``, and every process holds the whole fleet's outputs and
Jacobians. The host algebra after it (fits, noise models, tests, the fleet-wide
criterion and the verdict) then runs in every process on the same arrays, so every
process reaches the same verdict: a row's or a unit's evaluation does not depend on
the others evaluated with it (vmapped; bitwise the same), and the collectives come in
the same order everywhere because the program and its data are the same.

With one process, or fewer blocks than processes (a few changed rows evaluated
again), every process evaluates everything itself: no exchange.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import jax
import numpy as np
from jax._src import distributed  # JAX's own savers wait on its client this way


def evaluate_split(
    evaluate: Callable[[int, int], tuple[np.ndarray, ...]],
    num_items: int,
    block: int = 1,
) -> tuple[np.ndarray, ...]:
    """``evaluate(0, num_items)``, computed by the processes of the cluster together.

    Args:
        evaluate: ``(start, stop) -> arrays``, each with ``stop - start`` items on
            its leading axis (the items ``start .. stop - 1``); deterministic, and
            an item's values independent of the others in the call.
        num_items: items in all.
        block: the items are divided in whole blocks of this many (a static
            model's compiled chunk of rows), contiguous, process 0's first.

    Returns:
        The arrays of ``evaluate(0, num_items)``, the same in every process.
    """
    num_processes = jax.process_count()
    num_blocks = -(-num_items // block)
    if num_processes == 1 or num_blocks < num_processes:
        return tuple(evaluate(0, num_items))
    # imported here: one process never needs the cluster's code (nor h5py)
    from jax.experimental import multihost_utils

    from jaxcal.fleet.distributed import process_share

    blocks = np.arange(num_blocks)
    bounds = []
    for process in range(num_processes):
        mine = process_share(blocks, process, num_processes)
        bounds.append((int(mine[0]) * block, min(int(mine[-1] + 1) * block, num_items)))
    size = max(stop - start for start, stop in bounds)
    start, stop = bounds[jax.process_index()]
    local = [np.asarray(a) for a in evaluate(start, stop)]
    for a in local:
        if a.shape[:1] != (stop - start,):
            raise ValueError(
                f"evaluate_split: evaluate({start}, {stop}) returned an array of "
                f"shape {a.shape}, expected {stop - start} items on its first axis"
            )
    # one exchange of bytes: each array padded to the largest share (the same shape
    # in every process, process_allgather's contract), booleans as bytes; the
    # fleet's Jacobians are the diagnosis's memory: one copy of them at a time
    kinds = [(a.dtype, (size,) + a.shape[1:]) for a in local]
    sizes = [
        int(np.prod(shape)) * np.dtype(_wire(dtype)).itemsize for dtype, shape in kinds
    ]
    flat = np.zeros(sum(sizes), np.uint8)
    offset = 0
    for a, nbytes in zip(local, sizes, strict=True):
        wire = np.ascontiguousarray(a, _wire(a.dtype)).view(np.uint8).ravel()
        flat[offset : offset + wire.size] = wire
        offset += nbytes
    del local, wire
    _wait_for_all()
    stacked = np.asarray(multihost_utils.process_allgather(flat, tiled=False))
    del flat
    out, offset = [], 0
    for (dtype, shape), nbytes in zip(kinds, sizes, strict=True):
        pieces = [
            stacked[p, offset : offset + nbytes]
            .view(_wire(dtype))
            .reshape(shape)[: b - a]
            for p, (a, b) in enumerate(bounds)
        ]
        out.append(np.concatenate(pieces).astype(dtype, copy=False))
        offset += nbytes
    return tuple(out)


def _wire(dtype) -> np.dtype:
    """The type an array travels as (``bool`` as ``uint8``)."""
    return np.dtype(np.uint8) if dtype == np.bool_ else np.dtype(dtype)


# How long a process waits at an exchange for the others. The CPU collectives
# (gloo) give up after 30 s, and a process can fall further behind than that (it
# compiles a program the other read from the disk cache, or the machine is busy):
# the exchange starts once every process has reached it (a process that died
# holds the others at most this long).
WAIT_FOR_ALL_S = 1800
_BARRIERS = itertools.count()  # the same sequence in every process


def _wait_for_all() -> None:
    """Block until every process reaches this point (the cluster's coordination
    service, not a collective: no 30 s limit)."""
    client = distributed.global_state.client
    if client is not None:
        barrier = f"jaxcal.diagnosis.data.sharding.{next(_BARRIERS)}"
        client.wait_at_barrier(barrier, timeout_in_ms=WAIT_FOR_ALL_S * 1000)
