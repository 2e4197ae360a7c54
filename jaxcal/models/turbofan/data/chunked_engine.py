"""Solving generated rows with the engine in fixed-size chunks, and the noise variants.

The data-set builders (:mod:`jaxcal.models.turbofan.data.builders`) produce rows of (w,
theta) in file order; this module turns them into engine outputs with bounded memory and
one compiled engine call:

* :func:`iter_chunks` re-cuts row blocks of any size into chunks of ``chunk_size`` rows;
* :func:`solve_rows` pads a chunk to ``chunk_size`` (so the jitted engine sees one
  shape), solves it, re-solves samples that did not converge from the solution of the
  nearest converged sample of the same flight (Newton warm start), and raises a
  ``ValueError`` naming unit, cycle and w if any remain: nothing is written as NaN;
* :func:`perturb_outputs` applies the paper's noise variants with one PRNG key per
  (unit, cycle, sample), so results do not depend on chunking.

Samples are solved independently (the engine vmaps a per-sample Newton solve), so a
sample's outputs do not depend on which other rows share its chunk; only a warm-started
re-solve uses a neighbour, and only for samples that failed from their first start.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Iterator
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.data.noise import add_output_noise, add_sensor_noise_snr, apply_output_bias
from jaxcal.models.turbofan.physics import cycle
from jaxcal.models.turbofan.physics.constants import (
    CONDITION_NAMES,
    HEALTH_NAMES,
    MEASURED_SENSOR_NAMES,
    sensor_index,
)
from jaxcal.models.turbofan.physics.engine import Engine

NUM_UNKNOWNS = cycle.NUM_UNKNOWNS  # size of the Newton unknown vector (EngineInfo.z)


class RowBlock(NamedTuple):
    """``R`` rows to solve (host-side numpy), in file order."""

    w: np.ndarray  # [R, 4] operating conditions (CONDITION_NAMES)
    theta: np.ndarray  # [R, 10] health modifiers (HEALTH_NAMES)
    z0: np.ndarray  # [R, 9] Newton start
    unit: np.ndarray  # [R] int unit id
    cycle: np.ndarray  # [R] int flight cycle
    fc: np.ndarray  # [R] int flight class (fleet) / flight trajectory (scenarios)
    hs: np.ndarray  # [R] int health state (1 normal, 0 abnormal degradation)
    rul: np.ndarray  # [R] int remaining useful life [cycles]
    step: np.ndarray  # [R] int sample index within the flight

    @property
    def num_rows(self) -> int:
        """Number of rows ``R``."""
        return int(self.unit.shape[0])


def concat_rows(blocks: Iterable[RowBlock]) -> RowBlock:
    """Row blocks stacked in order."""
    return RowBlock(*(np.concatenate(cols) for cols in zip(*blocks, strict=True)))


def take_rows(block: RowBlock, index) -> RowBlock:
    """The rows of ``block`` picked by a numpy index (slice, mask, integers)."""
    return RowBlock(*(a[index] for a in block))


def evaluate_engine(engine: Engine, w, theta, z0):
    """Engine outputs of one chunk.

    Args:
        engine: the engine (a pytree: jit compiles once per engine configuration).
        w: [B, 4] conditions; theta: [B, 10] modifiers; z0: [B, 9] Newton starts.

    Returns:
        (x [B, S] in SENSOR_NAMES order, converged [B] bool, z [B, 9] solutions).
    """
    x, info = engine.evaluate(w, theta, z0=z0)
    return x, info.converged, info.z


# Created once per process, so that every build (and every test) shares the compiled
# engine: one compile per engine configuration and chunk size.
jit_evaluate_engine = jax.jit(evaluate_engine)


def iter_chunks(
    blocks: Iterable[RowBlock], size: int
) -> Iterator[tuple[RowBlock | None, bool]]:
    """Re-cut row blocks into chunks of ``size`` rows (the last one may be shorter).

    Yields:
        ``(chunk, False)`` for every chunk, and ``(None, True)`` after each input block
        has been consumed (a progress tick).
    """
    pending, count = [], 0
    for block in blocks:
        pending.append(block)
        count += block.num_rows
        while count >= size:
            rows = concat_rows(pending)
            pending, count = [take_rows(rows, slice(size, None))], count - size
            yield take_rows(rows, slice(0, size)), False
        yield None, True
    if count:
        yield concat_rows(pending), False


def _nearest_converged(ok: np.ndarray, group: np.ndarray) -> np.ndarray:
    """For every row, the index of the nearest converged row, same flight first."""
    n = ok.size
    idx, good = np.arange(n), np.flatnonzero(ok)
    pos = np.searchsorted(good, idx)
    left = good[np.clip(pos - 1, 0, good.size - 1)]
    right = good[np.clip(pos, 0, good.size - 1)]
    dist_left = np.abs(idx - left) + np.where(group[left] == group, 0, n)
    dist_right = np.abs(right - idx) + np.where(group[right] == group, 0, n)
    return np.where(dist_left <= dist_right, left, right)


def _failure_message(engine, rows, bad, where: str, max_retries: int) -> str:
    i = int(np.flatnonzero(bad)[0])
    w = dict(zip(CONDITION_NAMES, np.round(rows.w[i], 6).tolist(), strict=True))
    theta = {n: float(v) for n, v in zip(HEALTH_NAMES, rows.theta[i], strict=True) if v}
    return (
        f"engine {engine.name!r} did not converge for {int(bad.sum())} of "
        f"{rows.num_rows} samples of {where} after {max_retries} warm-started "
        f"retries (nothing is written as NaN); first: unit {rows.unit[i]}, cycle "
        f"{rows.cycle[i]}, sample {rows.step[i]}, w={w}, theta={theta or 'healthy'}"
    )


def solve_rows(
    evaluate, engine, rows: RowBlock, *, chunk_size: int, max_retries: int, where: str
) -> tuple[np.ndarray, np.ndarray, int]:
    """Engine outputs of at most ``chunk_size`` rows, solved as one padded chunk.

    Args:
        evaluate: ``(engine, w, theta, z0) -> (x, converged, z)``, e.g.
            :data:`jit_evaluate_engine`.
        engine: the engine.
        rows: 1 to ``chunk_size`` rows.
        chunk_size: the fixed batch size of every engine call.
        max_retries: rounds of warm-started re-solves of non-converged samples.
        where: names the chunk in error messages.

    Returns:
        (x [R, S], z [R, 9], number of rows that needed a re-solve).

    Raises:
        ValueError: naming unit, cycle and w when samples remain non-converged.
    """
    n = rows.num_rows
    if not 1 <= n <= chunk_size:
        raise ValueError(f"solve_rows needs 1..{chunk_size} rows, got {n}")
    pad = np.minimum(np.arange(chunk_size), n - 1)  # repeat the last row: one shape
    w, theta, z0 = rows.w[pad], rows.theta[pad], rows.z0[pad]
    x, ok, z = (np.array(a) for a in evaluate(engine, w, theta, z0))
    group = rows.unit[pad] * (1 << 20) + rows.cycle[pad]  # one flight per group
    num_retried = int(np.sum(~ok[:n]))
    for _ in range(max_retries):
        bad = ~ok
        if not bad[:n].any() or not ok.any():
            break
        start = np.where(bad[:, None], z[_nearest_converged(ok, group)], z)
        x2, ok2, z2 = (np.asarray(a) for a in evaluate(engine, w, theta, start))
        fix = bad & ok2
        x[fix], z[fix], ok[fix] = x2[fix], z2[fix], True
    if not ok[:n].all():
        raise ValueError(_failure_message(engine, rows, ~ok[:n], where, max_retries))
    return x[:n], z[:n], num_retried


def solve_all(evaluate, engine, rows: RowBlock, *, chunk_size: int, max_retries: int):
    """:func:`solve_rows` over any number of rows, chunk by chunk.

    Returns:
        (x [R, S], z [R, 9], number of rows that needed a re-solve).
    """
    xs, zs, retried = zip(
        *(
            solve_rows(
                evaluate,
                engine,
                chunk,
                chunk_size=chunk_size,
                max_retries=max_retries,
                where="the healthy reference pass",
            )  # fmt: skip
            for chunk, _ in iter_chunks([rows], chunk_size)
            if chunk is not None
        ),
        strict=True,
    )
    return np.concatenate(xs), np.concatenate(zs), sum(retried)


def reference_stats(x: np.ndarray) -> dict[str, np.ndarray]:
    """Per-sensor ``mean``, ``std`` (floored at 1e-12) and ``power`` = mean(x**2).

    Args:
        x: [N, S] engine outputs of the reference pass.

    Returns:
        dict of [S] arrays.
    """
    return {
        "mean": x.mean(0),
        "std": np.maximum(x.std(0), 1e-12),
        "power": np.square(x).mean(0),
    }


def perturb_outputs(key, x, unit, cycle, step, stats, bias, sigma, snr_db):
    """The data-set noise variants, applied as bias, then output noise, then sensors.

    ``x * bias`` (paper: F(w, theta) x 1.02) and ``x + N(0, sigma)`` in units normalised
    by the reference mean / std (paper: F + N(0, 0.1)) act on every model output;
    white noise at ``snr_db`` against the reference signal power (the AWGN definition,
    paper: 70 dB) acts on the measured sensors X_s only. Row ``i`` draws from
    ``fold_in(fold_in(fold_in(key, unit_i), cycle_i), step_i)``. The settings are
    traced scalars, so every variant shares one compiled function; a variant that is
    off (bias 1, sigma 0, snr_db inf) leaves ``x`` bit for bit unchanged.

    Args:
        key: the data set's noise key.
        x: [B, S] clean outputs (SENSOR_NAMES order).
        unit: [B] int; cycle: [B] int; step: [B] int (row identity).
        stats: :func:`reference_stats` of the reference pass.
        bias: [] factor (1: none).
        sigma: [] normalised noise std (0: none).
        snr_db: [] SNR in dB (inf: none).

    Returns:
        [B, S] perturbed outputs.
    """
    fold = jax.random.fold_in
    keys = jax.vmap(lambda u, c, s: fold(fold(fold(key, u), c), s))(unit, cycle, step)
    pairs = jax.vmap(jax.random.split)(keys)  # [B, 2]
    key_out, key_sensor = pairs[:, 0], pairs[:, 1]
    x = apply_output_bias(x, bias)
    noise = functools.partial(
        add_output_noise, sigma=sigma, mean=stats["mean"], std=stats["std"]
    )
    x = jnp.where(sigma > 0, jax.vmap(noise)(key_out, x), x)
    cols = jnp.asarray(sensor_index(MEASURED_SENSOR_NAMES))
    power = stats["power"][cols]
    noisy = jax.vmap(
        lambda k, r: add_sensor_noise_snr(k, r, snr_db, signal_power=power)
    )(key_sensor, x[:, cols])
    return x.at[:, cols].set(jnp.where(jnp.isfinite(snr_db), noisy, x[:, cols]))


jit_perturb_outputs = jax.jit(perturb_outputs)
