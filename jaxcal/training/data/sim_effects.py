"""Undeclared effects put into simulated training units, so that a policy learns to
hold under model error.

A filter is exact only where its model is: a biased sensor, a drifting gain or
coloured noise is read as a parameter change. A policy can learn to discount them,
but only if it trains on them. :func:`add_effects` gives a share of the simulated
units one effect each, drawn from the kinds of the diagnosis's table that act on the
outputs (:mod:`jaxcal.diagnosis.kinds.table`), at sizes in units of each output's noise
std:

* ``bias``: a constant offset on one output, from an onset to the unit's end;
* ``step``: the same offset from an onset in the unit's second half;
* ``drift``: an offset growing linearly from zero at the onset;
* ``gain``: a multiplicative error ``x (1 + g)`` on one output, ``g`` sized so
  that ``g |x|`` is the same number of noise stds;
* ``ar1``: the unit's noise coloured, ``e_t = phi e_{t-1} + sqrt(1 - phi^2) n_t``
  (the same marginal std, ``phi`` drawn in [0.5, 0.9]) on every output.

Only the noisy outputs change: the cost's target stays the model's noise-free output
(:mod:`jaxcal.training.data.simulated`), so tracking an effect is never rewarded, and
the true theta stays the label.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

KINDS = ("bias", "step", "drift", "gain", "ar1")


def add_effects(
    rng: np.random.Generator,
    noisy: np.ndarray,
    clean: np.ndarray,
    lengths: np.ndarray,
    noise_std: np.ndarray,
    share: float,
    sizes: tuple[float, float] = (1.0, 4.0),
) -> tuple[np.ndarray, list[str]]:
    """``(noisy', kinds)``: ``noisy`` ``[U, T, S]`` with one effect in a ``share``
    of its units (the rest unchanged); ``kinds`` ``[U]`` names each unit's effect
    (``"none"``).

    Args:
        rng: the draws (which units, kind, output, onset, size).
        noisy: the simulated outputs, clean + white noise of ``noise_std``.
        clean: their noise-free outputs (the gain's level, the noise to colour).
        lengths: ``[U]`` valid rows per unit.
        noise_std: ``[S]`` the white noise std.
        share: the share of units that carry an effect, in [0, 1].
        sizes: the range of an offset's size in noise stds (drawn uniformly).
    """
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"simulate.effects must be in [0, 1], got {share}")
    out = noisy.copy()
    kinds = ["none"] * noisy.shape[0]
    carriers = np.flatnonzero(rng.random(noisy.shape[0]) < share)
    for u in carriers:  # host-side data preparation, once per run
        kind = KINDS[rng.integers(len(KINDS))]
        kinds[u] = kind
        n = int(lengths[u])
        s = rng.integers(noisy.shape[2])
        size = rng.uniform(*sizes) * noise_std[s] * rng.choice([-1.0, 1.0])
        first = n // 2 if kind == "step" else int(rng.integers(0, max(n // 2, 1)))
        ramp = np.zeros(n)
        ramp[first:] = 1.0
        if kind == "drift":
            ramp[first:] = np.arange(n - first) / max(n - first - 1, 1)
        if kind in ("bias", "step", "drift"):
            out[u, :n, s] += size * ramp
        elif kind == "gain":
            level = np.mean(np.abs(clean[u, :n, s])) + 1e-12
            out[u, :n, s] += (size / level) * clean[u, :n, s] * ramp
        else:  # ar1: the same marginal std, coloured
            phi = rng.uniform(0.5, 0.9)
            white = (noisy[u, :n] - clean[u, :n]) / noise_std
            gain = np.sqrt(1 - phi**2)
            # stationary from the first row: y_0 = e_0 (zi = (1 - gain) e_0)
            coloured, _ = lfilter(
                [gain], [1.0, -phi], white, axis=0, zi=(1 - gain) * white[:1]
            )
            out[u, :n] = clean[u, :n] + coloured * noise_std
    return out, kinds
