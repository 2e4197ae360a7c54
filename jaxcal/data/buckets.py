"""Units padded in buckets of similar length: memory that grows with the rows.

:meth:`Dataset.padded <jaxcal.data.dataset.Dataset.padded>` pads every unit to the
longest, so one unit of 100,000 rows beside 2,000 one-row units asks for
``2001 x 100,000`` cells. :func:`bucket_units` groups the units so that no group is
padded to more than :data:`MAX_PADDING` times its rows, and each group is padded to
its own longest unit; a fleet that already fits (units of similar length) stays one
group, exactly :meth:`Dataset.padded`, so its results are unchanged.

Grouping: units sorted by length, longest first; a group takes the next unit while
``units x longest <= MAX_PADDING x rows`` still holds. A unit longer than half the
group's longest always fits, so each new group's longest is at most half the last
one's: at most ``log2(longest) + 1`` groups (compiled shapes), cells at most
``MAX_PADDING`` times the rows. A group of under :data:`MIN_GROUP_SHARE` of the
fleet's rows then joins the group before it, if that one's cells stay within
``2 MAX_PADDING`` of its rows: a program of its own would cost more. Each group
keeps the units' order of first appearance; :meth:`Buckets.to_rows` scatters
per-group ``[U_b, T_b, ...]`` values back to the data set's rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.data.padded import Padded

MAX_PADDING = 2.0  # padded cells of a group / its rows
# a group of fewer rows than this share of the fleet's joins the group before it while
# that one's cells stay within twice MAX_PADDING of its rows: each group is a program
# compiled and loaded of its own (the turbofan's: ~30 s to compile, ~0.4 GB resident,
# results/loop/profile.md), more than a few padded cells cost
MIN_GROUP_SHARE = 1.0 / 16.0


class Buckets(NamedTuple):
    """A data set's units as padded groups (module docstring).

    Attributes:
        parts: the groups, each a :class:`~jaxcal.data.padded.Padded` whose ``rows``
            index the whole data set's rows.
        num_rows: ``N``, the data set's rows.
    """

    parts: tuple[Padded, ...]
    num_rows: int

    @property
    def dtype(self):
        return self.parts[0].w.dtype

    @property
    def unit_ids(self) -> np.ndarray:
        """``[U]`` unit ids in the order of the groups."""
        return np.concatenate([p.unit_ids for p in self.parts])

    def to_rows(self, values: Sequence[np.ndarray], fill=np.nan) -> np.ndarray:
        """Per-group ``[U_b, T_b, ...]`` values -> ``[N, ...]`` in the data's row
        order (padded cells dropped; rows no group holds get ``fill``)."""
        values = [np.asarray(v) for v in values]
        if len(values) != len(self.parts):
            raise ValueError(f"expected {len(self.parts)} groups, got {len(values)}")
        first = values[0]
        out = np.full((self.num_rows,) + first.shape[2:], fill, dtype=first.dtype)
        for part, value in zip(self.parts, values, strict=True):
            out[part.rows[part.mask]] = value[part.mask]
        return out

    def from_rows(self, values: np.ndarray, fill=0) -> list[np.ndarray]:
        """``[N, ...]`` row values -> per-group ``[U_b, T_b, ...]`` (``fill`` on
        padding)."""
        values = np.asarray(values)
        parts = []
        for part in self.parts:
            cell = np.full(part.mask.shape + values.shape[1:], fill, values.dtype)
            cell[part.mask] = values[part.rows[part.mask]]
            parts.append(cell)
        return parts


def bucket_units(
    data: Dataset, dtype=np.float64, max_padding: float | None = None
) -> Buckets:
    """``data``'s units in padded groups of similar length (module docstring).

    Args:
        data: the rows.
        dtype: float dtype of ``w``, ``x`` (and ``theta``).
        max_padding: at most this many padded cells per row in a group (>= 1;
            default :data:`MAX_PADDING`).

    Returns:
        :class:`Buckets`; one group, equal to ``data.padded(dtype)``, when the whole
        fleet already fits.
    """
    max_padding = MAX_PADDING if max_padding is None else max_padding
    if not max_padding >= 1.0:
        raise ValueError(f"max_padding must be >= 1, got {max_padding}")
    groups = _group_units(data, max_padding)
    if len(groups) == 1:
        return Buckets((data.padded(dtype),), data.num_rows)
    parts = []
    for units in groups:
        idx = np.flatnonzero(np.isin(data.unit, units))
        part = data.take(idx).padded(dtype)
        rows = np.where(part.mask, idx[np.maximum(part.rows, 0)], -1)
        parts.append(part._replace(rows=rows))
    return Buckets(tuple(parts), data.num_rows)


def _group_units(data: Dataset, max_padding: float) -> list[np.ndarray]:
    """Unit ids per group (the module docstring's rule), longest group first."""
    ids, lengths = np.unique(data.unit, return_counts=True)
    if ids.size and ids.size * lengths.max() <= max_padding * lengths.sum():
        return [ids]
    order = np.argsort(-lengths, kind="stable")
    groups, current, longest, rows = [], [], 0, 0
    for i in order:
        n = int(lengths[i])
        if current and (len(current) + 1) * longest > max_padding * (rows + n):
            groups.append(np.asarray(current))
            current, rows = [], 0
        if not current:
            longest = n
        current.append(ids[i])
        rows += n
    groups.append(np.asarray(current))
    return _fold_small(groups, dict(zip(ids, lengths, strict=True)), max_padding)


def _fold_small(groups, length: dict, max_padding: float) -> list[np.ndarray]:
    """``groups`` with each one of under :data:`MIN_GROUP_SHARE` of the rows joined
    to the group before it, while that one's cells stay within ``2 max_padding`` of
    its rows (the groups longest first, so the one before sets the padded length)."""
    total = sum(length.values())
    out = [groups[0]]
    for group in groups[1:]:
        rows = sum(length[u] for u in group)
        merged = np.concatenate([out[-1], group])
        cells = merged.size * length[out[-1][0]]
        small = rows < MIN_GROUP_SHARE * total
        if small and cells <= 2.0 * max_padding * sum(length[u] for u in merged):
            out[-1] = merged
        else:
            out.append(group)
    return out
