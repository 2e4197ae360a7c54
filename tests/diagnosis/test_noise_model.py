"""The diagnosis's noise model: AR(p) colour, exact prewhitening, the fit's bias.

Coloured noise along each unit's rows is the first thing measured data do that the
old white-noise diagnosis did not expect (issue 24): these tests pin the pieces the
likelihoods now stand on.
"""

import types

import numpy as np
import pytest
from statsmodels.tsa.arima_process import arma_acf

from jaxcal.diagnosis.data.synthetic import ar1_noise
from jaxcal.diagnosis.residuals.noise import NoiseModel, ar_rows, ljung_box_p, positions
from jaxcal.diagnosis.residuals.noise_fit import fit_noise


def _rows(units, length, rng, num_w=2):
    n = units * length
    unit = np.repeat(np.arange(units), length)
    return types.SimpleNamespace(
        w=rng.uniform(size=(n, num_w)),
        tau=np.tile(np.arange(length), units) / 100.0,
        unit=unit,
        starts=np.arange(units + 1) * length,
        cycle=np.tile(np.arange(length), units).astype(float),
        num_units=units,
        num_rows=n,
    )


@pytest.mark.parametrize("phi", [[0.8], [0.6, 0.25], [0.5, -0.3, 0.2]])
def test_whitening_is_the_inverse_cholesky_of_the_ar_covariance(phi):
    """For every row position, the whitening rows turn the stationary AR(p)
    covariance of a unit into the identity (exact first rows, no approximation)."""
    phi = np.asarray(phi)
    n = 12
    acf = arma_acf(np.r_[1.0, -phi], [1.0], lags=n)
    cov = acf[np.abs(np.subtract.outer(np.arange(n), np.arange(n)))]
    model = NoiseModel.white(np.ones(1), "given")
    ar = np.zeros((1, 3))
    ar[0, : phi.size] = phi
    model = model._replace(ar=ar, order=np.array([phi.size]))
    eye = np.eye(n)[:, None, :]  # [n rows, 1 output, n columns]
    w = model.whiten(eye, np.arange(n))[:, 0, :]
    np.testing.assert_allclose(w @ cov @ w.T, np.eye(n), atol=1e-10)
    assert ar_rows(phi).shape == (phi.size + 1, phi.size + 1)


def test_colour_and_level_are_recovered_and_the_residual_is_white():
    rng = np.random.default_rng(0)
    data = _rows(4, 400, rng)
    sigma = np.array([2.0, 0.5])
    e = ar1_noise(rng, (data.num_rows, 2), data.unit, 0.7) * sigma
    e[:, 1] = rng.standard_normal(data.num_rows) * sigma[1]  # the second is white
    model = fit_noise(e, data)
    assert model.order[0] == 1 and model.ar[0, 0] == pytest.approx(0.7, abs=0.06)
    assert model.order[1] == 0
    np.testing.assert_allclose(model.sigma, sigma, rtol=0.1)
    white = model.whiten(e, positions(data.starts, data.num_rows))
    assert np.all(ljung_box_p(white) > 0.01)
    np.testing.assert_allclose(white.std(0), 1.0, atol=0.08)
    # the raw coloured residual is not white: the test sees it
    assert ljung_box_p(e / sigma)[0] < 1e-6


def test_ljung_box_is_statsmodels_to_the_last_bit():
    """``ljung_box_p`` forms only the lags it reads (statsmodels forms all N: O(N^2)
    on a fleet's concatenated rows) and must give acorr_ljungbox's p-values exactly:
    the diagnosis's reports were made with them."""
    from statsmodels.stats.diagnostic import acorr_ljungbox

    rng = np.random.default_rng(3)
    for n, lags in ((4, 10), (37, 10), (600, 10), (600, 3)):
        e = rng.standard_normal((n, 4))
        e[:, 1] = np.cumsum(e[:, 1])  # coloured: p near 0
        e[:, 3] = 2.0  # constant: p = 1, not tested
        want = np.ones(4)
        h = min(lags, max(n // 5, 1))
        for s in range(3):
            want[s] = acorr_ljungbox(e[:, s], lags=[h])["lb_pvalue"].iloc[0]
        np.testing.assert_array_equal(ljung_box_p(e, lags), want)


def test_what_a_flexible_fit_absorbs_is_given_back():
    """A per-unit spline fit on short units absorbs the low frequencies of coloured
    noise; uncorrected, colour and level come out low (issue 24's false alarms)."""
    rng = np.random.default_rng(1)
    data = _rows(6, 100, rng)
    t = np.linspace(0, 1, 100)
    basis = np.stack([t**k for k in range(5)], 1)  # 5 smooth functions per unit
    cols = np.zeros((data.num_rows, 1, 5))
    estimates, raw_estimates = [], []
    for _ in range(10):
        e = ar1_noise(rng, (data.num_rows, 1), data.unit, 0.7)
        resid = np.empty_like(e)
        for u in range(data.num_units):
            sl = slice(u * 100, (u + 1) * 100)
            coef = np.linalg.lstsq(basis, e[sl, 0], rcond=None)[0]
            resid[sl, 0] = e[sl, 0] - basis @ coef
            cols[sl, 0] = basis
        raw_estimates.append(fit_noise(resid, data).ar[0, 0])
        estimates.append(fit_noise(resid, data, cols=cols).ar[0, 0])
    raw_error = abs(np.mean(raw_estimates) - 0.7)
    assert raw_error > 0.06  # the bias is real ...
    assert abs(np.mean(estimates) - 0.7) < 0.5 * raw_error  # ... and mostly given back


def test_a_noise_model_within_the_tolerance_has_settled():
    """The noise passes stop when the refitted model is the one in use (pipeline
    NOISE_SETTLED): a level, a coefficient or an order that moved is a change."""
    old = NoiseModel.white(np.array([1.0, 2.0]), "estimated")
    old = old._replace(ar=np.array([[0.5, 0, 0], [0, 0, 0]]), order=np.array([1, 0]))
    assert old.settled(old, 0.0)
    assert old.with_sigma([1.005, 1.99], "estimated").settled(old, 0.01)
    assert not old.with_sigma([1.02, 2.0], "estimated").settled(old, 0.01)
    moved = old._replace(ar=np.array([[0.52, 0, 0], [0, 0, 0]]))
    assert not moved.settled(old, 0.01)
    assert not old._replace(order=np.array([1, 1])).settled(old, 0.01)


def _whiten_table_wide(model, arr, position):
    """The whitening as one pass of the whole array per lag over the full table:
    the reference the chunked form must equal to the bit."""
    from jaxcal.diagnosis.residuals.noise import MAX_ORDER

    scale = model.sigma * np.sqrt(model.inflation)
    extra = (1,) * (arr.ndim - 2)
    table = model.filter_table(position)
    out = table[:, :, 0].reshape(table.shape[:2] + extra) * arr
    for k in range(1, MAX_ORDER + 1):
        coef = table[k:, :, k].reshape((arr.shape[0] - k, arr.shape[1]) + extra)
        if np.any(coef):
            out[k:] += coef * arr[:-k]
    return out / scale.reshape((1, -1) + extra)


@pytest.mark.parametrize("shape", [(), (7,), (3, 2)])
def test_whitening_in_chunks_is_the_table_form_to_the_bit(shape, monkeypatch):
    """Units shorter than the AR order, a unit of one row, orders 0-3 per output,
    NaN and -0.0 entries: the same bits (signs of zero and NaNs included), with
    chunks of a few rows so that lags cross their edges."""
    import jaxcal.diagnosis.residuals.noise as noise

    monkeypatch.setattr(noise, "CHUNK_CELLS", 1)  # 64-row chunks
    rng = np.random.default_rng(3)
    lengths = np.array([1, 2, 150, 3, 97, 64, 65])
    starts = np.r_[0, np.cumsum(lengths)]  # with the end
    position = positions(starts, int(lengths.sum()))
    order = np.array([0, 1, 2, 3, 3])
    ar = np.zeros((5, noise.MAX_ORDER))
    for s, p in enumerate(order):
        ar[s, :p] = rng.uniform(-0.4, 0.6, p) / max(p, 1)
    model = NoiseModel(rng.uniform(0.5, 2.0, 5), ar, order,
                       np.where(order == 0, 1.3, 1.0), "estimated",
                       np.full(5, np.nan))  # fmt: skip
    arr = rng.normal(size=(position.size, 5) + shape)
    arr[10, 2] = np.nan
    arr[rng.random(arr.shape) < 0.05] = -0.0
    new = model.whiten(arr, position)
    ref = _whiten_table_wide(model, arr, position)
    assert np.array_equal(new, ref, equal_nan=True)
    assert np.array_equal(np.signbit(new), np.signbit(ref))


def test_an_output_whitened_alone_is_its_column_of_the_whole():
    """``take([s])`` then whitening the one output gives the whole's column ``s``
    (an output's rows are filtered with its own coefficients only): the numbers the
    discrepancy's per-output cross-validation reads without whitening the others."""
    rng = np.random.default_rng(5)
    lengths = np.array([2, 150, 97, 65])
    starts = np.r_[0, np.cumsum(lengths)]
    position = positions(starts, int(lengths.sum()))
    order = np.array([0, 1, 3, 2])
    ar = np.zeros((4, 3))
    for s, p in enumerate(order):
        ar[s, :p] = rng.uniform(-0.4, 0.6, p) / max(p, 1)
    model = NoiseModel(rng.uniform(0.5, 2.0, 4), ar, order, np.array([1.3, 1, 1, 1.1]),
                       "estimated", np.full(4, np.nan))  # fmt: skip
    arr = rng.normal(size=(position.size, 4, 6))
    whole = model.whiten(arr, position)
    for s in range(4):
        alone = model.take([s]).whiten(arr[:, [s]], position)
        assert np.array_equal(alone, whole[:, [s]])
