"""The one padded container: a data set's units as ``[U, T, ...]`` streams.

Units have different lengths, but compiled code needs static shapes: :class:`Padded`
holds every unit padded to a common length ``T`` with its valid length, so that
calibrators, training, evaluation and the fleet runners all read one type. The
readers fill it, :meth:`jaxcal.data.dataset.Dataset.padded` (any model's rows, units
in order of first appearance, remembering each cell's row) and
:func:`jaxcal.models.turbofan.data.datasets.read_ncmapss_padded` (turbofan units in
ascending id order, with their flight numbers); simulations of units build it directly.
Padding repeats each unit's last valid row (never zeros a model would choke on) and is
masked out. It is a ``NamedTuple`` of arrays (``None`` for what a source lacks), so it
is a pytree that jitted code can take whole.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Padded(NamedTuple):
    """``U`` units padded to ``T`` steps (rows ``t < lengths[u]`` are data).

    Attributes:
        w: ``[U, T, W]`` conditions. x: ``[U, T, S]`` outputs.
        theta: ``[U, T, P]`` true parameters (labels, for scoring only), or ``None``
            when the data carry no true values.
        lengths: ``[U]`` int32 valid steps per unit.
        unit_ids: ``[U]`` unit id of each row of the arrays.
        rows: ``[U, T]`` int64 index of each cell into the source's rows (-1 on
            padding), or ``None`` when the source does not map results back.
        cycle: ``[U, T]`` int64 flight (cycle) number of each step, repeated on
            padding, or ``None`` when the source has none.
    """

    w: np.ndarray
    x: np.ndarray
    theta: np.ndarray | None
    lengths: np.ndarray
    unit_ids: np.ndarray
    rows: np.ndarray | None = None
    cycle: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        """``[U, T]`` bool, True on valid steps (``t < lengths[u]``)."""
        return np.arange(self.x.shape[1])[None, :] < self.lengths[:, None]

    @property
    def num_samples(self) -> int:
        """Number of valid steps over all units."""
        return int(self.lengths.sum())

    def to_rows(self, values: np.ndarray, num_rows: int, fill=np.nan) -> np.ndarray:
        """``[U, T, ...]`` per-step values back to ``[N, ...]`` in the source's row
        order (the padded cells are dropped; needs ``rows``)."""
        values = np.asarray(values)
        mask = self.mask
        out = np.full((num_rows,) + values.shape[2:], fill, dtype=values.dtype)
        out[self.rows[mask]] = values[mask]
        return out
