"""The autocovariance bias of a fit's residual (noise_fit.projection_bias) against its
definition, with dense matrices: ``tr(J_k (P Sigma P^T - P Sigma - Sigma P^T)) / N_k``
(issue 43 rewrote its lag sums for speed; the numbers must not move)."""

from types import SimpleNamespace

import numpy as np
from statsmodels.tsa.arima_process import arma_acf

from jaxcal.diagnosis.residuals.noise import MAX_ORDER, NoiseModel, positions
from jaxcal.diagnosis.residuals.noise_fit import pair_counts, projection_bias


def _noise(sigma, phi):
    ar = np.zeros((len(sigma), MAX_ORDER))
    order = np.array([len(p) for p in phi])
    for s, p in enumerate(phi):
        ar[s, : len(p)] = p
    num_s = len(sigma)
    return NoiseModel(np.asarray(sigma, float), ar, order, np.ones(num_s), "given",
                      np.full(num_s, np.nan))  # fmt: skip


def _dense_bias(data, cols, fit, noise, max_lag):
    """The definition, unit by unit, with the stacked (row, output) vector."""
    n, num_s, _ = cols.shape
    out = np.zeros((num_s, max_lag + 1))
    eye = np.eye(num_s)
    for u in range(len(data.starts) - 1):
        sl = slice(data.starts[u], data.starts[u + 1])
        m = sl.stop - sl.start
        p_u = np.arange(m)
        trend = np.concatenate(
            [eye[None] * np.ones((m, 1, 1)), eye[None] * data.tau[sl, None, None]], 2
        )
        d = np.concatenate([cols[sl], trend], axis=2).reshape(m * num_s, -1)
        basis = np.eye(m * num_s).reshape(m, num_s, m * num_s)
        w_mat = fit.whiten(basis, p_u).reshape(m * num_s, m * num_s)
        v = w_mat.T @ w_mat
        proj = d @ np.linalg.pinv(d.T @ v @ d) @ d.T @ v
        sigma = np.zeros((m * num_s, m * num_s))
        lag = np.abs(np.subtract.outer(np.arange(m), np.arange(m)))
        for s in range(num_s):
            acf = arma_acf(np.r_[1.0, -noise.ar[s, : noise.order[s]]], [1.0], m)
            idx = np.arange(m) * num_s + s
            sigma[np.ix_(idx, idx)] = noise.sigma[s] ** 2 * acf[lag]
        bias = proj @ sigma @ proj.T - proj @ sigma - sigma @ proj.T
        for k in range(min(max_lag, m - 1) + 1):
            for s in range(num_s):
                rows = np.arange(k, m) * num_s + s
                out[s, k] += np.trace(bias[rows][:, rows - k * num_s])
    return out / np.maximum(pair_counts(data.starts, max_lag), 1)


def test_projection_bias_is_its_definition():
    rng = np.random.default_rng(3)
    starts = np.array([0, 9, 21])
    n, num_s, q, max_lag = 21, 2, 3, 4
    tau = np.concatenate([np.linspace(0, 1, 9), np.linspace(0, 1.5, 12)])
    data = SimpleNamespace(starts=starts, num_units=2, tau=tau)
    cols = rng.normal(size=(n, num_s, q))
    fit = _noise([1.3, 0.7], [[0.5], [0.3, -0.2]])
    noise = _noise([0.9, 1.1], [[0.6], []])
    assert positions(starts, n)[9] == 0
    got = projection_bias(data, cols, fit, noise, max_lag)
    want = _dense_bias(data, cols, fit, noise, max_lag)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    assert np.abs(want).max() > 1e-3  # the fit absorbs something: not a 0 == 0 test
