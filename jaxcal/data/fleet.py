"""Padded per-unit arrays of a :class:`~jaxcal.data.record.Record`, and normalisation.

Engine units have different lengths, but jitted code needs static shapes (STYLE §2.4):
:func:`to_fleet` pads every unit to a common length ``T`` on the host and carries a
``[U, T]`` validity mask. :func:`fit_norm_stats` gives per-column mean / std of
``w`` and ``x`` over the valid rows only, as the problem's one
:class:`~jaxcal.problem.Normalisation`; :func:`normalise` / :func:`denormalise` are
pure and jittable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxcal.data.normalisation import Normalisation
from jaxcal.data.record import Record
from jaxcal.physics.constants import HEALTH_NAMES
from jaxcal.precision import float_dtype


@struct.dataclass
class Fleet:
    """A fleet of ``U`` units padded to ``T`` time steps.

    Padded steps repeat the unit's last valid row (not zeros), so that code evaluated
    on them (the engine model, a network) sees a physical operating point and cannot
    produce NaNs that would leak into gradients through ``jnp.where``; use ``mask`` to
    ignore them.

    Attributes:
        w: ``[U, T, 4]`` operating conditions (alt ft, Mach, TRA %, T2 degR).
        x: ``[U, T, S]`` sensors, named by ``x_names``.
        theta: ``[U, T, 10]`` health modifiers; zeros when ``has_theta`` is False.
        mask: ``[U, T]`` bool, True on real (non-padded) steps.
        lengths: ``[U]`` int32 number of valid steps per unit.
        unit_ids: ``[U]`` int32 unit id of each row, ascending.
        cycle: ``[U, T]`` int32 flight number of each step (repeated on padding).
        x_names: static sensor names, ``S`` of them.
        has_theta: static; False when the source had no ground truth.
    """

    w: jax.Array
    x: jax.Array
    theta: jax.Array
    mask: jax.Array
    lengths: jax.Array
    unit_ids: jax.Array
    cycle: jax.Array
    x_names: tuple[str, ...] = struct.field(pytree_node=False, default=())
    has_theta: bool = struct.field(pytree_node=False, default=True)


def to_fleet(record: Record, max_len: int | None = None) -> Fleet:
    """Pad a record into per-unit arrays (host side: numpy, then one transfer).

    Args:
        record: rows of any number of units; the rows of a unit are taken in record
            order (file order is time order).
        max_len: common length ``T``. ``None``: the longest unit. Units longer than
            ``max_len`` keep their first ``max_len`` rows.

    Returns:
        A :class:`Fleet` with units in ascending id order; floats in the current JAX
        float dtype (float64 under x64).
    """
    n = record.num_rows
    if n == 0:
        raise ValueError("to_fleet needs a record with at least one row")
    unit_ids, inverse, counts = np.unique(
        record.unit, return_inverse=True, return_counts=True
    )
    order = np.argsort(inverse, kind="stable")  # group by unit, keep time order
    longest = int(counts.max())
    if max_len is None:
        max_len = longest
    elif int(max_len) < 1:
        raise ValueError(f"max_len must be >= 1 or None, got {max_len}")
    max_len = int(max_len)
    lengths = np.minimum(counts, max_len)

    # Index of the source row for every (unit, step): edge padding repeats the last row.
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    steps = np.minimum(np.arange(max_len)[None, :], lengths[:, None] - 1)
    source = order[starts[:, None] + steps]  # [U, T]

    dtype = float_dtype()
    theta = (
        record.theta[source]
        if record.theta is not None
        else np.zeros((len(unit_ids), max_len, len(HEALTH_NAMES)))
    )
    return Fleet(
        w=jnp.asarray(record.w[source], dtype=dtype),
        x=jnp.asarray(record.x[source], dtype=dtype),
        theta=jnp.asarray(theta, dtype=dtype),
        mask=jnp.asarray(np.arange(max_len)[None, :] < lengths[:, None]),
        lengths=jnp.asarray(lengths, dtype=jnp.int32),
        unit_ids=jnp.asarray(unit_ids, dtype=jnp.int32),
        cycle=jnp.asarray(record.cycle[source], dtype=jnp.int32),
        x_names=record.x_names,
        has_theta=record.theta is not None,
    )


def _masked_mean_std(values: jax.Array, mask: jax.Array, min_std: float):
    """Mean / std over the valid ``[U, T]`` entries of ``values`` ``[U, T, K]``."""
    weight = mask[..., None].astype(values.dtype)
    count = jnp.maximum(weight.sum(axis=(0, 1)), 1.0)
    mean = (values * weight).sum(axis=(0, 1)) / count
    var = (jnp.square(values - mean) * weight).sum(axis=(0, 1)) / count
    # A scale-aware floor: constant columns (C-MAPSS s1 = 518.67) must not blow up to
    # 1e10 after normalisation, and the floor must not depend on the column's unit.
    floor = min_std * jnp.maximum(1.0, jnp.abs(mean))
    return mean, jnp.maximum(jnp.sqrt(var), floor)


def fit_norm_stats(fleet: Fleet, *, min_std: float = 1e-6) -> Normalisation:
    """Per-column mean and std of ``w`` and ``x`` over the valid steps of ``fleet``.

    Args:
        fleet: padded data; padded steps (``mask`` False) are ignored.
        min_std: relative floor: ``std >= min_std * max(1, |mean|)``, so constant
            columns normalise to 0 instead of dividing by zero.

    Returns:
        :class:`Normalisation` with ``w_*`` ``[4]`` and ``x_*`` ``[S]``.
    """
    w_mean, w_std = _masked_mean_std(fleet.w, fleet.mask, min_std)
    x_mean, x_std = _masked_mean_std(fleet.x, fleet.mask, min_std)
    return Normalisation(w_mean=w_mean, w_std=w_std, x_mean=x_mean, x_std=x_std)


def normalise(fleet: Fleet, stats: Normalisation) -> Fleet:
    """Standardise ``w`` and ``x``: ``(value - mean) / std`` per column.

    Args:
        fleet: padded data in physical units (padding is transformed too, harmlessly).
        stats: from :func:`fit_norm_stats`.

    Returns:
        The fleet with normalised ``w`` ``[U, T, 4]`` and ``x`` ``[U, T, S]``.
    """
    return fleet.replace(
        w=(fleet.w - stats.w_mean) / stats.w_std,
        x=(fleet.x - stats.x_mean) / stats.x_std,
    )


def denormalise(fleet: Fleet, stats: Normalisation) -> Fleet:
    """Inverse of :func:`normalise`: ``value * std + mean`` per column.

    Args:
        fleet: fleet with normalised ``w`` and ``x``.
        stats: the statistics used to normalise it.

    Returns:
        The fleet with ``w`` and ``x`` back in physical units.
    """
    return fleet.replace(
        w=fleet.w * stats.w_std + stats.w_mean,
        x=fleet.x * stats.x_std + stats.x_mean,
    )
