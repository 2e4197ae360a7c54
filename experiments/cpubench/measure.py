"""Timing, machine-state and figure helpers shared by the benchmark sections.

* :func:`time_repeats` times a blocking callable several times and returns a
  :class:`Timing` (seconds per repeat and the work done in each), from which rates and
  per-item latencies are read as median and best (fastest repeat).
* :func:`figure` builds one reported figure: our value, its peer and the ratio, with the
  convention used everywhere in the JSON: ``ratio > 1`` means jaxcal is better (a rate
  divided by the peer's rate, or the peer's time divided by ours). A peer without a
  number carries a ``reason`` instead, and so does the figure.
* :class:`CpuWatch` reads ``/proc/stat`` around a section: the steal fraction and how
  busy the machine was, which say how much to trust the timings (the machine is shared).
* :func:`x64` switches JAX's float64 flag for one section and restores it; the engine
  and the UKF need float64, the networks run in float32 as in training.
* :func:`concurrently` runs the warm-ups (compilations) of a section side by side.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import importlib
import statistics
import time
from collections.abc import Callable, Iterator
from typing import Any

import jax


@dataclasses.dataclass(frozen=True)
class Timing:
    """Wall times of repeated runs of the same work.

    Attributes:
        seconds: wall time of each repeat.
        work: items done per repeat (samples, steps, updates, unit-steps).
    """

    seconds: tuple[float, ...]
    work: float

    @property
    def median_s(self) -> float:
        """Median seconds per repeat."""
        return statistics.median(self.seconds)

    @property
    def min_s(self) -> float:
        """Fastest repeat in seconds."""
        return min(self.seconds)

    def rate(self) -> tuple[float, float]:
        """Items per second: (median, best)."""
        return self.work / self.median_s, self.work / self.min_s

    def per_item_us(self) -> tuple[float, float]:
        """Microseconds per item: (median, best)."""
        return 1e6 * self.median_s / self.work, 1e6 * self.min_s / self.work


def time_repeats(fn: Callable[[], Any], *, repeats: int, work: float = 1.0) -> Timing:
    """Times ``repeats`` calls of ``fn``; ``fn`` must block until its work is done.

    Args:
        fn: the work (call ``jax.block_until_ready`` inside for JAX outputs).
        repeats: number of timed calls (warm up, i.e. compile, before).
        work: items each call processes.

    Returns:
        :class:`Timing`.
    """
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        seconds.append(time.perf_counter() - start)
    return Timing(tuple(seconds), float(work))


def time_interleaved(
    fns: dict[str, Callable[[], Any]], *, repeats: int, work: dict[str, float]
) -> dict[str, Timing]:
    """Times several blocking callables in turn, one repeat of each per round.

    On a shared machine the load changes from second to second; alternating ours and
    the peer's runs exposes both to the same load, so their ratio is meaningful even
    when the absolute numbers drift.

    Args:
        fns: name -> blocking callable.
        repeats: rounds (each callable runs once per round).
        work: name -> items per call.

    Returns:
        name -> :class:`Timing`.
    """
    seconds: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            seconds[name].append(time.perf_counter() - start)
    return {name: Timing(tuple(s), float(work[name])) for name, s in seconds.items()}


def concurrently(*fns: Callable[[], Any]) -> list[Any]:
    """Runs the callables in threads and returns their results in order.

    For warm-ups only, never around timings: XLA releases the GIL while it compiles,
    so the programs of a section compile side by side. A cold run compiles about ten
    programs of 10 to 100 s each; on two cores shared with other jobs, compiling them
    one after the other is most of the bench's wall time. The first error is raised.
    """
    with concurrent.futures.ThreadPoolExecutor(max_workers=len(fns)) as pool:
        futures = [pool.submit(fn) for fn in fns]
        return [future.result() for future in futures]


def blocking(fn: Callable[..., Any], *args: Any) -> Callable[[], Any]:
    """``fn(*args)`` wrapped so that the call returns only when JAX has finished."""
    return lambda: jax.block_until_ready(fn(*args))


def peer(
    name: str, value: float, unit: str, best: float | None = None, **extra: Any
) -> dict:
    """A peer measured in this run (``best``: its fastest repeat, same unit)."""
    return {"name": name, "value": value, "best": best, "unit": unit, **extra}


def missing_peer(name: str, reason: str) -> dict:
    """A peer that has no number here, and why."""
    return {"name": name, "value": None, "reason": reason}


def published_peer(name: str, value: float, unit: str, source: str) -> dict:
    """A reference number from a publication: never measured in this run."""
    return {"name": name, "value": value, "unit": unit, "published": True,
            "source": source}  # fmt: skip


def figure(
    value: float | None,
    unit: str,
    better: str,
    peer_info: dict,
    *,
    best: float | None = None,
    reason: str | None = None,
    **extra: Any,
) -> dict:
    """One reported number with its peer and ``ratio`` (> 1: jaxcal is better).

    Args:
        value: our median figure (``None`` when not measured; give ``reason``).
        unit: its unit (the peer's value must be in the same unit).
        better: ``"higher"`` (rates) or ``"lower"`` (times).
        peer_info: from :func:`peer`, :func:`missing_peer` or :func:`published_peer`.
        best: our figure from the fastest repeat, if any.
        reason: why ``value`` or the ratio is missing.
        **extra: further context stored with the figure.

    Returns:
        The figure dict: ``value``, ``best``, ``unit``, ``better``, ``peer``, ``ratio``
        (median / median), ``ratio_best`` (best / best, when both exist) and ``reason``
        when the ratio is ``None``.
    """
    if better not in ("higher", "lower"):
        raise ValueError(f"better must be 'higher' or 'lower', got {better!r}")

    def ratio(ours: float | None, theirs: float | None) -> float | None:
        if ours is None or theirs is None or ours <= 0 or theirs <= 0:
            return None
        return ours / theirs if better == "higher" else theirs / ours

    out = {"value": value, "best": best, "unit": unit, "better": better,
           "peer": peer_info, "ratio": ratio(value, peer_info.get("value")),
           "ratio_best": ratio(best, peer_info.get("best"))}  # fmt: skip
    if out["ratio"] is None:
        out["reason"] = (
            reason
            or peer_info.get("reason")
            or ("not measured" if value is None else "peer has no number")
        )
    out.update(extra)
    return out


def skipped(reason: str) -> dict:
    """A figure that was not measured in this run (e.g. ``--quick``), and why."""
    return figure(None, "", "higher", missing_peer("-", reason), reason=reason)


IMPORT_SIDE_EFFECTS: dict[str, dict] = {}
"""JAX flags an optional peer changed on import (restored), by module name."""


def _jax_flags() -> dict[str, Any]:
    return {k: getattr(jax.config, k) for k in dir(jax.config) if k.startswith("jax_")}


def try_import(name: str) -> tuple[Any, str | None]:
    """``(module, None)``, or ``(None, reason)`` when the optional peer is absent.

    JAX flags the import changes are put back and recorded in
    :data:`IMPORT_SIDE_EFFECTS`: dynamax sets ``jax_default_matmul_precision`` on
    import, which would change the numerics of the sections after it and force every
    program compiled before it to compile again (the flag is part of the jit cache
    key), inside the timed loops.
    """
    before = _jax_flags()
    try:
        module = importlib.import_module(name)
    except Exception as err:  # any failure of an optional peer becomes a reason
        return None, (
            f"cannot import {name} ({type(err).__name__}: {err}); install the "
            "peers with: pip install torch==2.13.0 && pip install -e '.[bench]'"
        )
    after = _jax_flags()
    changed = {k: v for k, v in before.items() if after.get(k) != v}
    for flag, value in changed.items():
        IMPORT_SIDE_EFFECTS.setdefault(name, {})[flag] = {
            "set_to": after.get(flag),
            "restored_to": value,
        }
        jax.config.update(flag, value)
    return module, None


def _cpu_times() -> list[int] | None:
    try:
        with open("/proc/stat") as fh:
            return [int(v) for v in fh.readline().split()[1:9]]
    except (OSError, ValueError):
        return None


def _loadavg() -> float | None:
    try:
        with open("/proc/loadavg") as fh:
            return float(fh.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


class CpuWatch:
    """Machine state over a section, from ``/proc/stat`` (``None`` where unreadable).

    ``report()`` gives the steal fraction (time the hypervisor gave our vCPUs to
    someone else), the busy fraction of all cores (ours and other jobs') and the
    1-minute load average at the end.
    """

    def __init__(self) -> None:
        self._start = _cpu_times()
        self._wall = time.perf_counter()

    def report(self) -> dict:
        """State since construction: steal and busy fractions, load, seconds."""
        end = _cpu_times()
        out: dict[str, Any] = {
            "seconds": time.perf_counter() - self._wall,
            "loadavg_1min": _loadavg(),
            "steal_fraction": None,
            "busy_fraction": None,
        }
        if self._start is not None and end is not None:
            delta = [b - a for a, b in zip(self._start, end, strict=True)]
            total = sum(delta)
            if total > 0:
                idle = delta[3] + delta[4]  # idle + iowait
                out["steal_fraction"] = delta[7] / total
                out["busy_fraction"] = (total - idle) / total
        return out


@contextlib.contextmanager
def x64(enabled: bool) -> Iterator[None]:
    """JAX's float64 flag set to ``enabled`` inside the block, restored after."""
    previous = bool(jax.config.jax_enable_x64)
    jax.config.update("jax_enable_x64", enabled)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)
