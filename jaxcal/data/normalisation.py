"""The data's normalisation: per-column mean and std of the conditions and outputs.

:class:`Normalisation` is the one record of these statistics: ``w_n = (w - w_mean) /
w_std``, likewise for ``x``. It lives in the data layer, below the problem
(:class:`jaxcal.problem.Problem`, which carries the one normalisation of a
calibration and re-exports this class), and imports nothing of jaxcal.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# A constant channel (std below this, relative to its scale) is normalised by 1.
CONSTANT_REL_STD = 1e-12


class Normalisation(NamedTuple):
    """Training statistics: ``w_n = (w - w_mean) / w_std``, likewise for ``x``."""

    w_mean: np.ndarray  # [W]
    w_std: np.ndarray  # [W] > 0
    x_mean: np.ndarray  # [S]
    x_std: np.ndarray  # [S] > 0

    @classmethod
    def of(cls, w: np.ndarray, x: np.ndarray, dtype=np.float64) -> Normalisation:
        """Statistics of rows ``w [N, W]``, ``x [N, S]`` (a constant column gets 1),
        computed in ``dtype`` (``None``: the arrays' own, so a float32 run keeps the
        exact float32 statistics it always had). A NaN (a missing output of a partial
        row) is left out of its column's statistics."""
        return cls(*column_stats(w, dtype), *column_stats(x, dtype))


def column_stats(
    a: np.ndarray, dtype=np.float64, rel: float = CONSTANT_REL_STD
) -> tuple[np.ndarray, np.ndarray]:
    """``(mean, std)`` of each column of ``a [N, C]`` in ``dtype`` (``None``: the
    array's own), NaN left out, a column whose std is at most ``rel`` of its scale
    gets std 1: the arithmetic of :meth:`Normalisation.of` and of the networks'
    :func:`jaxcal.nets.mlp.fit_normalizer`."""
    a = np.asarray(a, dtype)
    if np.isnan(a).any():  # host branch: complete data keep their exact bits
        mean, std = np.nanmean(a, axis=0), np.nanstd(a, axis=0)
    else:
        mean, std = a.mean(axis=0), a.std(axis=0)
    tiny = std <= rel * np.maximum(np.abs(mean), 1.0)
    return mean, np.where(tiny, 1.0, std).astype(a.dtype)
