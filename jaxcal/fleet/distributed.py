"""Multi-process fleet calibration on JAX's distributed runtime (``jax.distributed``).

The multi-controller model: the same program runs in every process (one per host, or
several per host); :func:`initialize` connects them through a coordinator
(``host:port`` of process 0) before any JAX computation, after which ``jax.devices()``
lists every process's devices and one mesh spans them all
(:func:`~jaxcal.fleet.sharded.make_unit_mesh`). On CPU, cross-process collectives use
gloo over TCP (``jax_cpu_collectives_implementation``, gloo by default in jax 0.10), so
a localhost cluster of CPU processes works with no extra install.

Data never goes through process 0: each process takes its own share of the units
(:func:`process_share`, contiguous blocks by ``jax.process_index()``), builds its slice
of the global arrays with ``jax.make_array_from_process_local_data``, and the sharded
program runs on the global mesh. Results are gathered with ``process_allgather``, so
every process ends with the whole fleet's results (in the streaming path only one chunk
at a time); by convention process 0 alone writes files. Every collective (run, gather)
must be called by all processes in the same order.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh

from jaxcal.calibrators.interface import Calibrator, CalOutput
from jaxcal.fleet.sharded import (
    finish_units,
    make_unit_mesh,
    padded_size,
    start_units,
    units_per_process,
)
from jaxcal.typedefs import Array, PRNGKey

ENV_COORDINATOR = "JAXCAL_COORDINATOR"  # host:port of process 0
ENV_NUM_PROCESSES = "JAXCAL_NUM_PROCESSES"
ENV_PROCESS_ID = "JAXCAL_PROCESS_ID"


def process_settings(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    environ: Mapping[str, str] | None = None,
) -> tuple[str | None, int, int]:
    """Resolve the cluster settings from arguments, else ``JAXCAL_*`` variables.

    Args:
        coordinator: ``host:port`` or ``None``.
        num_processes: ``None`` reads ``JAXCAL_NUM_PROCESSES`` (default 1).
        process_id: ``None`` reads ``JAXCAL_PROCESS_ID`` (default 0).
        environ: variables to read (default ``os.environ``).

    Returns:
        ``(coordinator, num_processes, process_id)``, validated.
    """
    env = os.environ if environ is None else environ
    coordinator = coordinator or env.get(ENV_COORDINATOR) or None
    try:
        if num_processes is None:
            num_processes = int(env.get(ENV_NUM_PROCESSES, "1"))
        if process_id is None:
            process_id = int(env.get(ENV_PROCESS_ID, "0"))
    except ValueError as err:
        raise ValueError(
            f"{ENV_NUM_PROCESSES} and {ENV_PROCESS_ID} must be integers ({err})"
        ) from None
    _check_settings(coordinator, int(num_processes), int(process_id))
    return coordinator, int(num_processes), int(process_id)


def _check_settings(coordinator: str | None, num_processes: int, process_id: int):
    if num_processes < 1:
        raise ValueError(f"num_processes must be >= 1, got {num_processes}")
    if not 0 <= process_id < num_processes:
        raise ValueError(
            f"process_id must lie in [0, num_processes={num_processes}), "
            f"got {process_id}"
        )
    if num_processes > 1:
        host, sep, port = (coordinator or "").rpartition(":")
        if not (sep and host and port.isdigit() and 0 < int(port) < 65536):
            raise ValueError(
                f"coordinator must be 'host:port' (the address of process 0, e.g. "
                f"127.0.0.1:12355) when num_processes > 1, got {coordinator!r}"
            )


def initialize(
    coordinator: str | None,
    num_processes: int,
    process_id: int,
    *,
    local_device_count: int | None = None,
    timeout_s: int = 300,
) -> None:
    """Join (or, as process 0, start) a JAX cluster; call before any JAX computation.

    With ``num_processes == 1`` nothing is initialised (one process needs no
    coordinator). Every process must call this with the same ``coordinator`` and
    ``num_processes`` and its own ``process_id``; the call returns when all have
    connected, or raises after ``timeout_s``.

    Args:
        coordinator: ``host:port`` of process 0, reachable from every process.
        num_processes: processes in the cluster.
        process_id: this process, ``0 .. num_processes - 1``.
        local_device_count: CPU only: split this process's CPU into that many
            devices (sets ``jax_num_cpu_devices``, like
            ``XLA_FLAGS=--xla_force_host_platform_device_count``); ``None`` leaves it.
        timeout_s: how long to wait for the other processes.

    Raises:
        ValueError: bad settings (the message says which and the expected form).
        RuntimeError: JAX already ran a computation in this process, or the cluster
            could not be formed (the original error is chained).
    """
    _check_settings(coordinator, num_processes, process_id)
    if local_device_count is not None and int(local_device_count) < 1:
        raise ValueError(f"local_device_count must be >= 1, got {local_device_count}")
    try:
        if local_device_count is not None:
            jax.config.update("jax_num_cpu_devices", int(local_device_count))
        if num_processes == 1:
            return
        jax.distributed.initialize(
            coordinator_address=coordinator,
            num_processes=num_processes,
            process_id=process_id,
            initialization_timeout=int(timeout_s),
        )
    except (RuntimeError, ValueError) as err:
        raise RuntimeError(
            f"jax.distributed.initialize failed for process {process_id} of "
            f"{num_processes} with coordinator {coordinator!r}: {err}. It must run "
            "before any JAX computation (and before the backend is created, e.g. by "
            "jax.devices()), and every process must reach the coordinator."
        ) from err


def process_share(
    items: Sequence | np.ndarray,
    process_index: int | None = None,
    num_processes: int | None = None,
) -> np.ndarray:
    """This process's contiguous block of ``items`` (``numpy.array_split`` order).

    Args:
        items: e.g. the sorted unit ids of a file.
        process_index: default ``jax.process_index()``.
        num_processes: default ``jax.process_count()``.

    Returns:
        The block; block sizes differ by at most one, process 0's come first.
    """
    p = jax.process_index() if process_index is None else process_index
    n = jax.process_count() if num_processes is None else num_processes
    if not 0 <= p < n:
        raise ValueError(f"process_index must lie in [0, {n}), got {p}")
    return np.array_split(np.asarray(items), n)[p]


def calibrate_distributed(
    calibrator: Calibrator,
    w: Array,
    x: Array,
    mask: Array | None = None,
    *,
    keys: PRNGKey | None = None,
    mesh: Mesh | None = None,
    unroll: int = 1,
) -> CalOutput:
    """Calibrate a fleet whose units are split over processes; every process calls.

    Each process passes only its own units (e.g. those of :func:`process_share`); the
    fleet is their concatenation in process order. The per-process unit counts may
    differ; they are exchanged first, and every process pads to the largest.

    Args:
        calibrator: the method.
        w: ``[u, T, Wd]``, x: ``[u, T, S]``, mask: ``[u, T]`` or ``None``: this
            process's units (``u >= 1``; ``T`` and feature sizes equal everywhere).
        keys: ``[u]`` PRNG keys or ``None``.
        mesh: default :func:`~jaxcal.fleet.sharded.make_unit_mesh` over all devices.
        unroll: ``lax.scan`` unroll factor.

    Returns:
        ``CalOutput`` of host numpy arrays for the whole fleet, ``theta [U, T, P]``
        with ``U`` the sum of all processes' ``u``, in process order; the same in
        every process.
    """
    w, x = np.asarray(w), np.asarray(x)
    if w.ndim != 3 or x.ndim != 3 or w.shape[:2] != x.shape[:2] or w.shape[0] < 1:
        raise ValueError(
            f"calibrate_distributed: expected this process's w [u, T, Wd] and "
            f"x [u, T, S] with equal u >= 1, T; got w {w.shape}, x {x.shape}"
        )
    mask = np.ones(w.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != w.shape[:2]:
        raise ValueError(f"calibrate_distributed: mask must be [u, T] = {w.shape[:2]}")
    mesh = make_unit_mesh() if mesh is None else mesh
    counts = np.asarray(
        multihost_utils.process_allgather(np.array([w.shape[0]], np.int64))
    ).reshape(-1)
    offset = int(counts[: jax.process_index()].sum())
    size = padded_size(int(counts.max()), units_per_process(mesh))
    pending = start_units(
        calibrator, mesh, w, x, mask, offset + np.arange(w.shape[0]),
        size=size, keys=keys, unroll=unroll,
    )  # fmt: skip
    return finish_units(pending)[1]
