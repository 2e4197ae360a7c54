"""The screen's onset scan of a step in a static model: every onset of every unit at
once by suffix sums, against the per-unit scan that whitens each onset's column."""

from types import SimpleNamespace

import numpy as np

from jaxcal.diagnosis.fitting.screen import _RIDGE, Screen
from jaxcal.diagnosis.kinds.onsets import ONSET_CI
from jaxcal.diagnosis.residuals.noise import MAX_ORDER, NoiseModel, positions


def _screen(lengths, orders, seed=0, q=3):
    rng = np.random.default_rng(seed)
    starts = np.r_[0, np.cumsum(lengths)]
    n, s = int(starts[-1]), len(orders)
    ar = np.zeros((s, MAX_ORDER))
    for i, p in enumerate(orders):
        ar[i, :p] = [0.5, -0.2, 0.1][:p]
    level, inflation = rng.uniform(0.5, 2.0, s), rng.uniform(1.0, 1.5, s)
    noise = NoiseModel(level, ar, np.array(orders), inflation, "given",
                       np.full(s, np.nan))  # fmt: skip
    data = SimpleNamespace(
        starts=starts, unit=np.repeat(np.arange(len(lengths)), lengths),
        position=positions(starts, n), num_units=len(lengths), num_rows=n,
        noise=noise, x=np.zeros((n, s)),
    )  # fmt: skip
    screen = Screen.__new__(Screen)
    screen.data = data
    screen.used = rng.uniform(size=(n, s)) > 0.1
    screen.r = rng.normal(size=(n, s)) * screen.used
    screen._decl = rng.normal(size=(n, s, q)) * screen.used[:, :, None]
    screen._a_inv, screen._d = [], []
    for u in range(data.num_units):
        sl = slice(starts[u], starts[u + 1])
        dm = screen.decl[sl].reshape(-1, q)
        screen._a_inv.append(np.linalg.inv(dm.T @ dm + 1e-6 * np.eye(q)))
        screen._d.append(dm.T @ screen.r[sl].reshape(-1))
    screen._a_inv, screen._d = np.stack(screen._a_inv), np.stack(screen._d)
    raw = rng.normal(size=(n, s)) * screen.used
    return screen, raw


def _reference(screen, raw):
    """Each unit's onsets whitened one column each (the scan before suffix sums)."""
    data = screen.data
    pos, first, grid = data.position, data.starts[:-1], screen._grid()
    lr, est, var = (np.zeros(data.num_units) for _ in range(3))
    onset, ci = np.zeros(data.num_units, int), np.zeros((data.num_units, 2), int)
    best = np.zeros(raw.shape + (1,))
    for u in range(data.num_units):
        sl = slice(data.starts[u], data.starts[u + 1])
        steps = raw[sl, :, None] * (pos[sl][:, None] >= grid[u][None, :])[:, None, :]
        white = data.noise.whiten(steps, pos[sl])
        n, s, g = white.shape
        z = white.reshape(n * s, g)
        b = screen.decl[sl].reshape(n * s, -1).T @ z
        mm = np.sum(z * z, 0) - np.einsum("ig,ij,jg->g", b, screen._a_inv[u], b)
        ss = z.T @ screen.r[sl].reshape(-1) - b.T @ screen._a_inv[u] @ screen._d[u]
        stat = np.where(mm > _RIDGE, ss**2 / mm, 0.0)
        k = int(np.argmax(stat))
        lr[u], est[u], var[u] = stat[k], ss[k] / mm[k], 1.0 / mm[k]
        onset[u] = first[u] + grid[u, k]
        near = grid[u][stat >= stat[k] - ONSET_CI]
        ci[u] = first[u] + np.array([near.min(), near.max()])
        best[sl, :, 0] = white[:, :, k]
    return lr, est, var, onset, ci, best


def test_every_onset_at_once_is_each_onset_whitened_alone():
    # units shorter than the AR order, shorter than the grid and longer; AR orders
    # 0 to 3 (the transient rows of an onset reach into a unit's first rows)
    for orders in ([0, 1, 2, 3], [0, 0], [3, 1, 2]):
        screen, raw = _screen([3, 4, 6, 40, 300], orders)
        scores, best = screen._static_step(raw)
        lr, est, var, onset, ci, best_ref = _reference(screen, raw)
        np.testing.assert_allclose(scores.lr, lr, rtol=1e-9)
        np.testing.assert_allclose(scores.estimate, est, rtol=1e-9)
        np.testing.assert_allclose(scores.variance, var, rtol=1e-9)
        np.testing.assert_array_equal(scores.onset, onset)
        np.testing.assert_array_equal(scores.onset_ci, ci)
        np.testing.assert_array_equal(best, best_ref)  # each entry's bits
