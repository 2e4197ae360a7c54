"""Fleet calibration sharded over devices: a 1-D ``Mesh`` whose axis runs over units.

Units of a fleet never talk to each other, so the fleet axis ``U`` is embarrassingly
parallel: :func:`run_sharded` places ``[U, T, ...]`` arrays with
``NamedSharding(mesh, P("units"))`` and runs
:func:`~jaxcal.calibrators.interface.run_fleet` under ``jax.shard_map``: every device
executes the single-device program on its own block of ``U / D`` units, with no
collective at all. The per-unit arithmetic is therefore that of one device, and results
agree with the unsharded path to round-off (bit for bit in our tests). ``jit`` with
``in_shardings`` would let the SPMD partitioner reach the same program; ``shard_map``
states it and rules out surprise communication.

``U`` must be a multiple of the device count ``D``: :func:`pad_units` appends *dummy*
units that repeat the last real unit (so a model is only ever evaluated at physical
operating points, as with :class:`~jaxcal.data.padded.Padded`'s time padding) with an
all-False mask; their outputs are dropped. :func:`shard_units` builds global arrays with
``jax.make_array_from_process_local_data``, which is also the multi-process entry
(:mod:`jaxcal.fleet.distributed`): with one process the local data is the whole fleet.
:func:`gather_units` brings results back to the host, through ``process_allgather``
when some shards live in other processes. :func:`start_units` / :func:`finish_units`
chain them for one process's units (tagged with global positions) and are shared by the
multi-process and streaming paths; :func:`calibrate_sharded` is the one-process call.

Every entry takes an optional :class:`~jaxcal.calibrators.interface.SampleCheck`
(replicated on every device) and returns ``CalOutput.valid`` / ``.reason`` per sample:
a flagged sample (NaN, out of range) is skipped as in ``run_calibrator``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec

from jaxcal.calibrators.interface import Calibrator, CalOutput, SampleCheck, run_fleet
from jaxcal.typedefs import Array, PRNGKey, PyTree

UNITS_AXIS = "units"


def make_unit_mesh(devices: Sequence[Any] | None = None) -> Mesh:
    """A 1-D mesh named ``"units"`` over ``devices`` (default: all global devices).

    Devices are ordered by (process index, id), so each process owns one contiguous
    block of the unit axis; :func:`shard_units` relies on that for process-local data.

    Args:
        devices: JAX devices; ``None`` means ``jax.devices()`` (every process's).

    Returns:
        ``Mesh`` of shape ``(D,)`` with an ``Auto`` axis ``"units"``.
    """
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("make_unit_mesh: devices must name at least one device")
    ordered = sorted(devices, key=lambda d: (d.process_index, d.id))
    return Mesh(np.asarray(ordered), (UNITS_AXIS,), axis_types=(AxisType.Auto,))


def units_per_process(mesh: Mesh) -> int:
    """Multiple that each process's unit count must be: its device count in ``mesh``.

    Raises:
        ValueError: if processes own different numbers of devices (the unit axis
            could then not be split into equal process blocks).
    """
    counts: dict[int, int] = {}
    for device in mesh.devices.flat:
        counts[device.process_index] = counts.get(device.process_index, 0) + 1
    if len(set(counts.values())) != 1:
        raise ValueError(
            f"every process must contribute the same number of devices to the mesh, "
            f"got {counts}"
        )
    return next(iter(counts.values()))


def padded_size(num_units: int, multiple: int) -> int:
    """Smallest multiple of ``multiple`` that is ``>= max(num_units, 1)``."""
    if num_units < 0 or multiple < 1:
        raise ValueError(
            f"padded_size: need num_units >= 0 and multiple >= 1, "
            f"got {num_units}, {multiple}"
        )
    return max(1, -(-num_units // multiple)) * multiple


def pad_units(
    w: Array, x: Array, mask: Array, size: int, keys: PRNGKey | None = None
) -> tuple[Array, Array, Array, PRNGKey | None]:
    """Append dummy units so that the unit axis has length ``size``.

    A dummy repeats the last real unit's ``w``, ``x`` (and key) with ``mask`` all False:
    ``run_calibrator`` then never advances its state and outputs zeros, while the
    model is still evaluated at a physical operating point (no NaN, no slow solve).

    Args:
        w: ``[U, T, Wd]``. x: ``[U, T, S]``. mask: ``[U, T]`` bool.
        size: target number of units, ``>= U``.
        keys: ``[U]`` PRNG keys or ``None``.

    Returns:
        ``(w, x, mask, keys)`` with leading axis ``size`` (numpy in, numpy out).
    """
    num_units = w.shape[0]
    if num_units < 1 or size < num_units:
        raise ValueError(f"pad_units: need 1 <= U <= size, got U={num_units}, {size=}")
    if num_units == size:
        return w, x, mask, keys
    idx = np.minimum(np.arange(size), num_units - 1)
    real = (np.arange(size) < num_units)[:, None]
    mask = np.where(real, np.asarray(mask, bool)[idx], False)
    return w[idx], x[idx], mask, None if keys is None else keys[idx]


def shard_units(mesh: Mesh, local: PyTree) -> PyTree:
    """Global arrays sharded over ``"units"`` from this process's ``[u, ...]`` data.

    Every leaf's leading axis is this process's share of units; the global array
    concatenates the shares in process order (``jax.make_array_from_process_local_data``
    infers the global shape). With one process, ``local`` is the whole fleet.

    Args:
        mesh: from :func:`make_unit_mesh`.
        local: pytree of host arrays with equal leading size ``u``, a multiple of
            :func:`units_per_process`; the same ``u`` in every process.

    Returns:
        The pytree of global ``jax.Array`` s with ``NamedSharding(mesh, P("units"))``.
    """
    sharding = NamedSharding(mesh, PartitionSpec(UNITS_AXIS))
    multiple = units_per_process(mesh)
    sizes = {np.shape(leaf)[0] for leaf in jax.tree.leaves(local)}
    if len(sizes) != 1 or next(iter(sizes)) % multiple:
        raise ValueError(
            f"shard_units: every leaf needs the same leading size, a multiple of the "
            f"{multiple} local devices; got sizes {sorted(sizes)}"
        )
    return jax.tree.map(
        lambda a: jax.make_array_from_process_local_data(sharding, np.asarray(a)),
        local,
    )


def gather_units(tree: PyTree) -> PyTree:
    """Global arrays -> host numpy arrays holding every process's units.

    Fully addressable arrays (one process) are simply fetched; otherwise the shards are
    exchanged with ``multihost_utils.process_allgather`` (a collective: every process
    must call this, in the same order).
    """
    leaves = jax.tree.leaves(tree)
    if all(a.is_fully_addressable for a in leaves):
        return jax.tree.map(np.asarray, jax.device_get(tree))
    return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))


def run_sharded(
    calibrator: Calibrator,
    mesh: Mesh,
    w: Array,
    x: Array,
    mask: Array,
    keys: PRNGKey | None = None,
    *,
    unroll: int = 1,
    check: SampleCheck | None = None,
) -> CalOutput:
    """Jitted :func:`run_fleet` with every unit-axis array sharded over ``mesh``.

    Args:
        calibrator: the method (a static argument: reuse the same object, or each call
            recompiles).
        mesh: from :func:`make_unit_mesh`.
        w: ``[U, T, Wd]``, x: ``[U, T, S]``, mask: ``[U, T]``, keys: ``[U]`` or
            ``None``; ``U`` a multiple of the mesh size. Global arrays from
            :func:`shard_units`, or host arrays (then placed by ``jit``).
        unroll: ``lax.scan`` unroll factor.
        check: the valid input box (``None``: finiteness only), replicated.

    Returns:
        ``CalOutput`` of global arrays (``theta [U, T, P]``, ..., ``valid`` and
        ``reason [U, T]``), sharded like ``w``.
    """
    if w.shape[0] % mesh.size:
        raise ValueError(
            f"run_sharded: U = {w.shape[0]} units is not a multiple of the "
            f"{mesh.size} devices; pad with pad_units first"
        )
    # Typed keys travel as raw key data: plain uint32 arrays shard like any other.
    impl = None if keys is None else jax.random.key_impl(keys)
    key_data = None if keys is None else jax.random.key_data(keys)
    return _run_sharded_jit(calibrator, mesh, unroll, impl, w, x, mask, key_data, check)


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3))
def _run_sharded_jit(calibrator, mesh, unroll, impl, w, x, mask, key_data, check):
    spec = PartitionSpec(UNITS_AXIS)

    def local(w, x, mask, key_data, check):
        keys = None
        if key_data is not None:
            keys = jax.random.wrap_key_data(key_data, impl=impl)
        return run_fleet(calibrator, w, x, mask, keys=keys, unroll=unroll, check=check)

    # check_vma=False: the body has no collective, and the scan carry starts from
    # replicated constants (the prior) that become unit-varying after one step, which
    # the varying-axes type check would reject without changing any number.
    in_specs = (spec, spec, spec, spec, PartitionSpec())  # the check: replicated
    sharded = jax.shard_map(
        local, mesh=mesh, in_specs=in_specs, out_specs=spec, check_vma=False
    )
    return sharded(w, x, mask, key_data, check)


class PendingUnits(NamedTuple):
    """A dispatched run of :func:`start_units`: global arrays, maybe still computing."""

    index: Array  # [D * size] global positions, -1 for dummies
    out: CalOutput  # [D * size, T, ...]
    along: PyTree  # caller's per-unit arrays, [D * size, ...]


def start_units(
    calibrator: Calibrator,
    mesh: Mesh,
    w: Array,
    x: Array,
    mask: Array,
    index: Array,
    *,
    size: int,
    keys: PRNGKey | None = None,
    along: PyTree = None,
    unroll: int = 1,
    check: SampleCheck | None = None,
) -> PendingUnits:
    """Pad, place and dispatch this process's units; return without waiting.

    The building block of the single-process, multi-process and streaming paths. Each
    process passes its own units tagged with their positions ``index`` in a global unit
    order (``-1`` marks a dummy); every process must use the same ``size`` (one
    program) and call in the same order (the program is collective).

    Args:
        calibrator: the method (static: reuse the object to avoid recompiling).
        mesh: from :func:`make_unit_mesh`.
        w: ``[u, T, Wd]``, x: ``[u, T, S]``, mask: ``[u, T]``: this process's units.
        index: ``[u]`` int global positions of those units, ``-1`` for dummies.
        size: units per process after padding, a multiple of
            :func:`units_per_process` and ``>= u``.
        keys: ``[u]`` PRNG keys or ``None``.
        along: optional pytree of ``[u, ...]`` host arrays (ids, flight numbers,
            truth) that travel with the units and come back gathered with the results.
        unroll: ``lax.scan`` unroll factor.
        check: the valid input box (``None``: finiteness only).

    Returns:
        :class:`PendingUnits`; pass it to :func:`finish_units`.
    """
    index = np.asarray(index, np.int64)
    if index.shape != np.shape(w)[:1]:
        raise ValueError(f"start_units: index must be [u] = {np.shape(w)[:1]}")
    # Keys are placed as raw key data (host uint32), like every other input.
    impl = None if keys is None else jax.random.key_impl(keys)
    key_data = None if keys is None else np.asarray(jax.random.key_data(keys))
    w, x, mask, _ = pad_units(np.asarray(w), np.asarray(x), mask, size)
    idx = np.minimum(np.arange(size), index.shape[0] - 1)
    along, key_data = jax.tree.map(lambda a: np.asarray(a)[idx], (along, key_data))
    index = np.where(np.arange(size) < index.shape[0], index[idx], -1)
    placed = shard_units(mesh, (w, x, mask, index, along, key_data))
    w, x, mask, index, along, key_data = placed
    keys = None if impl is None else jax.random.wrap_key_data(key_data, impl=impl)
    out = run_sharded(calibrator, mesh, w, x, mask, keys, unroll=unroll, check=check)
    return PendingUnits(index=index, out=out, along=along)


def finish_units(pending: PendingUnits) -> tuple[np.ndarray, CalOutput, PyTree]:
    """Wait for a :func:`start_units` run and gather every process's real units.

    A collective when several processes take part: all must call it, in order.

    Returns:
        ``(positions [U_all], CalOutput, along)`` as host numpy arrays, dummies dropped
        and units in ascending global position.
    """
    index, out, along = gather_units(tuple(pending))
    real = np.flatnonzero(index >= 0)
    order = real[np.argsort(index[real], kind="stable")]
    take = lambda a: a[order]  # noqa: E731
    return index[order], jax.tree.map(take, out), jax.tree.map(take, along)


def calibrate_sharded(
    calibrator: Calibrator,
    w: Array,
    x: Array,
    mask: Array | None = None,
    *,
    keys: PRNGKey | None = None,
    mesh: Mesh | None = None,
    unroll: int = 1,
    check: SampleCheck | None = None,
) -> CalOutput:
    """Single-process fleet calibration over all local devices; the same result as
    ``jax.jit(run_fleet, static_argnums=0)(calibrator, w, x, mask, keys=keys)``.

    Args:
        calibrator: the method.
        w: ``[U, T, Wd]``. x: ``[U, T, S]``. mask: ``[U, T]`` bool or ``None``.
        keys: ``[U]`` PRNG keys for stochastic calibrators, else ``None``.
        mesh: default :func:`make_unit_mesh` over this process's devices.
        unroll: ``lax.scan`` unroll factor.
        check: the valid input box (``None``: finiteness only).

    Returns:
        ``CalOutput`` of host numpy arrays, ``theta [U, T, P]``, ``xhat [U, T, S]``,
        ``aux [U, T, ...]``, ``valid`` and ``reason [U, T]``.
    """
    w, x = np.asarray(w), np.asarray(x)
    if w.ndim != 3 or x.ndim != 3 or w.shape[:2] != x.shape[:2]:
        raise ValueError(
            f"calibrate_sharded: expected w [U, T, Wd] and x [U, T, S] with equal U, "
            f"T; got w {w.shape}, x {x.shape}"
        )
    mask = np.ones(w.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != w.shape[:2]:
        raise ValueError(f"calibrate_sharded: mask must be [U, T] = {w.shape[:2]}")
    if keys is not None and keys.shape != w.shape[:1]:
        raise ValueError(f"calibrate_sharded: keys must be [U] = {w.shape[:1]}")
    mesh = make_unit_mesh(jax.local_devices()) if mesh is None else mesh
    if len({d.process_index for d in mesh.devices.flat}) > 1:
        raise ValueError(
            "calibrate_sharded: the mesh spans several processes; use "
            "jaxcal.fleet.distributed.calibrate_distributed with each process's units"
        )
    size = padded_size(w.shape[0], mesh.size)
    pending = start_units(
        calibrator, mesh, w, x, mask, np.arange(w.shape[0]),
        size=size, keys=keys, unroll=unroll, check=check,
    )  # fmt: skip
    return finish_units(pending)[1]
