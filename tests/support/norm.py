"""The normalisation of a test's environment that has no problem to take it from."""

from __future__ import annotations

import numpy as np

from jaxcal.problem import Normalisation


def own_norm(w, x, lengths) -> Normalisation:
    """Mean and std of ``w [U, T, W]`` and ``x [U, T, S]`` over their own valid rows
    (``t < lengths[u]``), in their dtype: what a run's problem holds for its training
    units (:func:`jaxcal.training.data.calibration.training_norm`)."""
    w, x, lengths = np.asarray(w), np.asarray(x), np.asarray(lengths)
    valid = np.arange(x.shape[1])[None, :] < lengths[:, None]
    return Normalisation.of(w[valid], x[valid], dtype=None)
