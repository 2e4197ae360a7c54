"""The physics F over many samples at once, and the E2E baselines' training sets.

* :func:`evaluate_declared`: x = F(w, theta) for ``[N]`` samples of the declared
  parameters, in fixed-size chunks (one compiled engine call per chunk size); used for
  the model output of a model-free method (the E2E network's x-hat = F(w_t, theta_t),
  so that its tracking error means what the other methods' does) and for simulated
  labels.
* :func:`gather_units`: labelled units picked by id from the splits of a data set (the
  paper's E2E learns from the labels of units 1, 4, 7 and 9 of Dataset #1, §4.2).
* :func:`simulated_units`: "E2E-sim" (design/calibration.md), the same network trained
  on simulated labels: the training units' flights w flown again with random parameter
  paths over the whole action box, x = F(w, theta). No measured label is needed — the
  information the RL policy trains with (flights and the model), plus labels it makes.
"""

from __future__ import annotations

import jax
import numpy as np

from jaxcal.data.padded import Padded
from jaxcal.models.turbofan.data.chunked_engine import NUM_UNKNOWNS, jit_evaluate_engine
from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES, sensor_index
from jaxcal.problem import Problem


def evaluate_declared(
    engine, problem: Problem, w, theta, *, chunk_size: int = 8192
) -> tuple[np.ndarray, np.ndarray]:
    """F at ``N`` samples: the declared parameters set, the others at ``theta_base``.

    Calls the data generator's compiled engine
    (:data:`jaxcal.models.turbofan.data.chunked_engine. jit_evaluate_engine`, Newton
    started at the design point): with the generator's chunk size the program is shared
    with data generation. Needs float64 (``jax.enable_x64``) like every engine call.

    Args:
        engine: the loaded engine of ``problem.model.name``.
        problem: sensors, declared parameters, base values.
        w: ``[N, W]`` operating conditions.
        theta: ``[N, P]`` declared parameters.
        chunk_size: samples per engine call; the last chunk is padded by repeating its
            last row, so every call has one shape.

    Returns:
        ``(x [N, S] float64, converged [N] bool)``; a sample that did not converge or
        lies outside the envelope has ``converged = False`` (its x is unspecified).
    """
    w = np.asarray(w, np.float64)
    theta = np.asarray(theta, np.float64)
    if w.ndim != 2 or theta.ndim != 2 or w.shape[0] != theta.shape[0]:
        raise ValueError(
            f"expected w [N, W] and theta [N, P]; got {w.shape}, {theta.shape}"
        )
    if theta.shape[1] != len(problem.theta_names):
        raise ValueError(
            f"theta has {theta.shape[1]} columns, the problem declares "
            f"{list(problem.theta_names)}"
        )
    num = w.shape[0]
    full = np.broadcast_to(problem.theta_base, (num, len(HEALTH_NAMES))).copy()
    full[:, [HEALTH_NAMES.index(n) for n in problem.theta_names]] = theta
    cols = sensor_index(problem.output_names)
    x = np.zeros((num, len(cols)))
    ok = np.zeros(num, bool)
    for start in range(0, num, chunk_size):  # a loop over chunks, not samples
        rows = np.minimum(np.arange(start, start + chunk_size), num - 1)
        start_z = np.zeros((chunk_size, NUM_UNKNOWNS))
        out, converged, _ = jit_evaluate_engine(engine, w[rows], full[rows], start_z)
        n = min(chunk_size, num - start)
        x[start : start + n] = np.asarray(out)[:n][:, cols]
        ok[start : start + n] = np.asarray(converged)[:n]
    ok &= np.isfinite(x).all(axis=-1)
    return x, ok


def gather_units(splits: list[Padded | None], unit_ids) -> Padded:
    """The units ``unit_ids`` (in that order) from any of ``splits``, re-padded.

    Raises:
        ValueError: a unit id is in none of the splits.
    """
    found = {}
    for split in splits:
        if split is None:
            continue
        for i, u in enumerate(split.unit_ids):
            found.setdefault(int(u), (split, i))
    missing = [int(u) for u in unit_ids if int(u) not in found]
    if missing:
        raise ValueError(f"unit(s) {missing} are in no split; known: {sorted(found)}")
    picks = [found[int(u)] for u in unit_ids]
    longest = max(int(s.lengths[i]) for s, i in picks)

    def pad(array: np.ndarray) -> np.ndarray:
        # repeat the last row, as the data loader pads
        out = array[:longest]
        if out.shape[0] < longest:
            out = np.concatenate([out, np.repeat(out[-1:], longest - len(out), 0)])
        return out

    return Padded(
        w=np.stack([pad(s.w[i]) for s, i in picks]),
        x=np.stack([pad(s.x[i]) for s, i in picks]),
        theta=np.stack([pad(s.theta[i]) for s, i in picks]),
        lengths=np.array([s.lengths[i] for s, i in picks], np.int32),
        unit_ids=np.array([s.unit_ids[i] for s, i in picks], np.int64),
    )


def simulated_units(
    key,
    engine,
    problem: Problem,
    flights: Padded,
    *,
    max_samples: int,
    chunk_size: int = 8192,
) -> tuple[Padded, float]:
    """E2E-sim training data: the flights of ``flights`` with simulated labels.

    Each unit's theta moves linearly, over its valid samples, between two points drawn
    uniformly in the action box (a degradation path in any direction, so the labels
    cover the whole box, not only the paths seen in the data); x = F(w, theta). When
    the flights hold more than ``max_samples`` valid samples, a seeded subset of units
    is flown. Samples F could not solve are masked out.

    Args:
        key: PRNG key (unit subset, parameter paths).
        engine: the loaded engine.
        problem: the data set's problem (box, sensors, base values).
        flights: ``[U, T, ...]`` units whose ``w`` is flown (their x, theta unused).
        max_samples: budget of engine evaluations.
        chunk_size: see :func:`evaluate_declared`.

    Returns:
        ``(units, converged_share)``: simulated ``Padded`` (``lengths`` count the
        prefix of valid samples; unsolved samples are cut with their successors) and
        the share of samples that solved.
    """
    key_units, key_ends = jax.random.split(key)
    flights = subset_units(key_units, flights, max_samples)
    lengths = flights.lengths
    w = flights.w
    num_units, num_steps = w.shape[:2]
    low, high = problem.theta_low, problem.theta_high
    ends = np.asarray(jax.random.uniform(key_ends, (2, num_units, len(low))))
    ends = low + ends * (high - low)  # [2, U, P]
    steps = np.arange(num_steps)[None, :]
    frac = np.clip(steps / np.maximum(lengths - 1, 1)[:, None], 0.0, 1.0)
    theta = ends[0][:, None] + frac[..., None] * (ends[1] - ends[0])[:, None]
    valid = steps < lengths[:, None]
    x_flat, ok_flat = evaluate_declared(
        engine, problem, w[valid], theta[valid], chunk_size=chunk_size
    )
    x = np.zeros((num_units, num_steps, len(problem.output_names)))
    ok = np.zeros((num_units, num_steps), bool)
    x[valid], ok[valid] = x_flat, ok_flat
    # an unsolved sample ends its unit: E2E reads x_{t-1}, so no gap may be bridged
    solved_prefix = np.cumprod(ok, axis=1).sum(axis=1).astype(np.int32)
    units = Padded(
        w=w,
        x=x,
        theta=theta,
        lengths=solved_prefix,
        unit_ids=flights.unit_ids,
    )
    return units, float(ok_flat.mean())


def subset_units(key, units: Padded, max_samples: int) -> Padded:
    """A seeded subset of whole units holding at most ``max_samples`` valid samples
    (at least one unit), in their original order and re-padded."""
    order = np.asarray(jax.random.permutation(key, len(units.lengths)))
    budget = np.cumsum(units.lengths[order])
    keep = np.sort(order[: max(1, int(np.searchsorted(budget, max_samples, "right")))])
    longest = int(units.lengths[keep].max())
    return Padded(
        *(a[keep, :longest] for a in units[:3]),
        lengths=units.lengths[keep],
        unit_ids=units.unit_ids[keep],
    )
