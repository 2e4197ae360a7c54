"""Streaming fleet calibration: chunks of units in, results file out, bounded memory.

A fleet that does not fit in memory is cut into *global chunks* of ``chunk_units``
consecutive units (in a global unit order). Each process takes its share of every chunk
(``numpy.array_split`` by process index, :func:`plan_chunks`), so with one process a
chunk is simply ``chunk_units`` units. Every chunk is padded to the same shape
``[units_per_chunk, T, ...]`` per process, so the whole stream runs ONE compiled program
(:func:`~jaxcal.fleet.sharded.run_sharded`); ``T`` is fixed by the source (the longest
unit, or a bound given by the user).

:func:`calibrate_stream` overlaps reading with computing: it dispatches chunk ``k`` (JAX
dispatch is asynchronous), reads chunk ``k + 1`` from disk while the devices work, then
gathers chunk ``k`` and appends its valid rows to the output file
(:class:`~jaxcal.fleet.results.FleetResultWriter`: atomic, process 0 only). At any time
a process holds at most two input chunks and one gathered output chunk. Chunks come from
any iterable of :class:`UnitChunk`: :func:`iter_array_chunks` cuts in-memory arrays,
:func:`jaxcal.models.turbofan.fleet.iter_ncmapss_chunks` reads an N-CMAPSS file.
Units are independent, so chunked results equal one-shot results unit for unit.
A ``check`` (:class:`~jaxcal.calibrators.interface.SampleCheck`) flags and skips bad
samples; their flags go to the file and their counts per reason to the summary.
Rows with some outputs missing (NaN) are used by a calibrator that accepts them (UKF,
least squares) and skipped as ``x_partial`` by others; the file's ``partial`` column
and the summary's ``num_partial`` count them.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Mapping
from typing import NamedTuple

import numpy as np
from jax.sharding import Mesh

from jaxcal.calibrators.interface import Calibrator, SampleCheck, count_reasons
from jaxcal.fleet.results import FleetResultWriter
from jaxcal.fleet.sharded import (
    finish_units,
    padded_size,
    start_units,
    units_per_process,
)


class UnitChunk(NamedTuple):
    """This process's share of one global chunk (host numpy arrays).

    Attributes:
        index: ``[u]`` int64 positions of the units in the global unit order; ``-1``
            marks a dummy (a process whose share of the chunk is empty still runs,
            on a copy of a real unit, because the program is collective).
        unit_ids: ``[u]`` int64 unit ids.
        w: ``[u, T, Wd]``. x: ``[u, T, S]``. mask: ``[u, T]`` bool.
        cycle: ``[u, T]`` int64 flight numbers, or ``None``.
        extras: per-step arrays ``[u, T, ...]`` copied to the output (e.g.
            ``theta_true``); the same keys in every chunk.
    """

    index: np.ndarray
    unit_ids: np.ndarray
    w: np.ndarray
    x: np.ndarray
    mask: np.ndarray
    cycle: np.ndarray | None = None
    extras: Mapping[str, np.ndarray] | None = None


def plan_chunks(
    num_units: int, chunk_units: int, num_processes: int = 1
) -> list[list[np.ndarray]]:
    """Global unit positions of every (chunk, process) pair.

    Args:
        num_units: ``U`` units in the global order.
        chunk_units: units per global chunk (``>= 1``).
        num_processes: processes sharing each chunk.

    Returns:
        ``plan[k][p]``: int64 positions (possibly empty) that process ``p`` handles in
        chunk ``k``; contiguous, and in ascending order over ``(k, p)``.
    """
    if num_units < 1 or chunk_units < 1 or num_processes < 1:
        raise ValueError(
            "plan_chunks: need num_units, chunk_units and num_processes >= 1, got "
            f"{num_units}, {chunk_units}, {num_processes}"
        )
    starts = range(0, num_units, chunk_units)
    return [
        np.array_split(np.arange(a, min(a + chunk_units, num_units)), num_processes)
        for a in starts
    ]


def units_per_chunk(chunk_units: int, num_processes: int, mesh: Mesh) -> int:
    """Per-process units of every padded chunk: ``ceil(chunk_units / processes)``
    rounded up to a multiple of the process's device count."""
    share = -(-chunk_units // num_processes)
    return padded_size(share, units_per_process(mesh))


def iter_array_chunks(
    w: np.ndarray,
    x: np.ndarray,
    mask: np.ndarray,
    chunk_units: int,
    *,
    unit_ids: np.ndarray | None = None,
    cycle: np.ndarray | None = None,
    extras: Mapping[str, np.ndarray] | None = None,
    process_index: int = 0,
    num_processes: int = 1,
) -> Iterator[UnitChunk]:
    """Chunks of an in-memory fleet ``[U, T, ...]`` (this process's share of each).

    Args:
        w: ``[U, T, W]`` the whole fleet (each process may hold it, or only its units).
        x: ``[U, T, S]`` its outputs.
        mask: ``[U, T]`` its validity.
        chunk_units: units per global chunk.
        unit_ids: ``[U]`` ids (default ``0 .. U-1``).
        cycle: optional per-step array ``[U, T]``.
        extras: optional per-step arrays ``[U, T, ...]``.
        process_index: this process.
        num_processes: how many processes share the chunks.

    Yields:
        :class:`UnitChunk` s, one per global chunk.
    """
    num_units = np.shape(w)[0]
    unit_ids = np.arange(num_units) if unit_ids is None else np.asarray(unit_ids)
    for parts in plan_chunks(num_units, chunk_units, num_processes):
        pos = parts[process_index]
        index = pos
        if pos.size == 0:  # a dummy: the chunk's first unit, results discarded
            pos, index = parts[0][:1], np.full(1, -1)
        yield UnitChunk(
            index=index.astype(np.int64),
            unit_ids=unit_ids[pos].astype(np.int64),
            w=_take(w, pos),
            x=_take(x, pos),
            mask=_take(mask, pos).astype(bool),
            cycle=_take(cycle, pos),
            extras=None
            if extras is None
            else {k: _take(v, pos) for k, v in extras.items()},
        )


def _take(values, pos: np.ndarray):
    """Rows ``pos`` of a host array (``None`` stays ``None``)."""
    return None if values is None else np.asarray(values)[pos]


def calibrate_stream(
    calibrator: Calibrator,
    chunks: Iterable[UnitChunk],
    mesh: Mesh,
    *,
    size: int,
    writer: FleetResultWriter | None = None,
    unroll: int = 1,
    check: SampleCheck | None = None,
) -> dict:
    """Calibrate a stream of chunks with one compiled program; append to ``writer``.

    Every process must call this with chunk iterables of equal length (the run and the
    gather of each chunk are collective). Only the process that passes a ``writer``
    (process 0 by convention) writes.

    Args:
        calibrator: the method (a static argument of the compiled program).
        chunks: this process's :class:`UnitChunk` s, each with at most ``size`` units
            and the same ``T`` and feature sizes.
        mesh: from :func:`~jaxcal.fleet.sharded.make_unit_mesh`.
        size: padded units per process and chunk (:func:`units_per_chunk`).
        writer: an open :class:`FleetResultWriter`, or ``None`` (results discarded).
        unroll: ``lax.scan`` unroll factor.
        check: the valid input box (``None``: finiteness only).

    Returns:
        ``{"num_chunks", "num_units", "num_rows", "num_flagged", "flagged",
        "num_partial", "seconds", "rows_per_s"}`` over all processes (rows =
        unpadded time steps; ``flagged``: rows skipped per reason, ``num_flagged``
        their total; ``num_partial``: rows with missing outputs, used or not).
    """
    start = time.perf_counter()
    stats = {"num_chunks": 0, "num_units": 0, "num_rows": 0, "num_partial": 0}
    flagged = count_reasons([])
    iterator = iter(chunks)
    chunk = next(iterator, None)
    if chunk is None:
        raise ValueError("calibrate_stream: the chunk iterable is empty")
    while chunk is not None:
        if not 1 <= chunk.w.shape[0] <= size:
            raise ValueError(
                f"calibrate_stream: a chunk has {chunk.w.shape[0]} units; "
                f"need 1 .. size={size}"
            )
        along = {
            "unit_ids": chunk.unit_ids,
            "mask": chunk.mask,
            "cycle": chunk.cycle,
            "extras": dict(chunk.extras or {}),
        }
        pending = start_units(
            calibrator, mesh, chunk.w, chunk.x, chunk.mask, chunk.index,
            size=size, along=along, unroll=unroll, check=check,
        )  # fmt: skip
        # Dispatch is asynchronous: reading the next chunk overlaps with the devices.
        chunk = next(iterator, None)
        positions, out, rows = finish_units(pending)
        stats["num_chunks"] += 1
        stats["num_units"] += positions.size
        stats["num_rows"] += int(rows["mask"].sum())
        for name, count in count_reasons(out.reason, rows["mask"]).items():
            flagged[name] += count
        stats["num_partial"] += int(np.sum(out.partial & rows["mask"]))
        if writer is not None:
            writer.append(
                rows["unit_ids"], rows["mask"], out.theta, out.xhat, aux=out.aux,
                cycle=rows["cycle"], extras=rows["extras"], valid=out.valid,
                reason=out.reason, partial=out.partial,
            )  # fmt: skip
    return stream_summary(stats, flagged, time.perf_counter() - start)


def stream_summary(counts: dict, flagged: dict, seconds: float) -> dict:
    """:func:`calibrate_stream`'s summary of its ``counts`` (chunks, units, rows,
    partial rows), the rows ``flagged`` per reason and the ``seconds`` taken."""
    return {
        **counts,
        "num_flagged": sum(flagged.values()),
        "flagged": flagged,
        "seconds": seconds,
        "rows_per_s": counts["num_rows"] / max(seconds, 1e-12),
    }
