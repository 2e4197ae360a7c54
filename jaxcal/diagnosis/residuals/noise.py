"""The noise model of the diagnosis: a level and an AR(p) colour per output.

Measured noise is rarely white: a sensor's errors are correlated from one reading to
the next (a slow filter in the acquisition, a thermal lag, a wandering bias). A
diagnosis that treats rows as independent inflates every likelihood-ratio statistic
by the noise's long-run variance ratio (``(1 + phi) / (1 - phi)`` for AR(1): 9 at
``phi = 0.8``) and raises alarms on clean records. Here each output's noise is a
stationary AR(p) process along each unit's rows (``p <= max_order``, chosen by BIC),
and everything the diagnosis computes — fits, screens, tests, standard errors — is
done on the **prewhitened** residual (generalised least squares; Cochrane & Orcutt
1949, with the exact treatment of each unit's first rows of Prais & Winsten 1954 in
its AR(p) form: the innovations algorithm, Brockwell & Davis 1991, sec. 5.2).

The model is fitted to a calibration's residual by
:mod:`jaxcal.diagnosis.residuals.noise_fit`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
from scipy import stats
from statsmodels.tsa.arima_process import arma_acf
from statsmodels.tsa.stattools import levinson_durbin

MAX_ORDER = 3  # highest AR order tried
WHITENESS_LAGS = 10  # Ljung–Box lags of the whiteness checks


class NoiseModel(NamedTuple):
    """Per-output noise: marginal std and AR(p) colour along each unit's rows.

    Attributes:
        sigma: ``[S]`` marginal noise std (output units).
        ar: ``[S, MAX_ORDER]`` AR coefficients ``phi_1..phi_p`` (zeros beyond ``p``).
        order: ``[S]`` int, the AR order ``p`` (0: white).
        inflation: ``[S]`` >= 1, the HAC variance factor (1 where AR(p) fits).
        source: ``given``, ``reference`` or ``estimated``.
        whiteness_p: ``[S]`` Ljung–Box p-value of the whitened residual the model was
            fitted on (NaN when not fitted).
    """

    sigma: np.ndarray
    ar: np.ndarray
    order: np.ndarray
    inflation: np.ndarray
    source: str
    whiteness_p: np.ndarray

    @classmethod
    def white(cls, sigma, source: str) -> NoiseModel:
        """White noise of std ``sigma [S]``."""
        sigma = np.asarray(sigma, np.float64)
        num = sigma.shape[0]
        return cls(
            sigma, np.zeros((num, MAX_ORDER)), np.zeros(num, int), np.ones(num),
            source, np.full(num, np.nan),
        )  # fmt: skip

    @property
    def is_white(self) -> bool:
        """True when no output has colour or inflation."""
        return not (self.order.any() or np.any(self.inflation > 1.0))

    def take(self, keep) -> NoiseModel:
        """The model of the outputs ``keep`` (indices)."""
        keep = np.asarray(keep, int)
        return NoiseModel(
            self.sigma[keep], self.ar[keep], self.order[keep], self.inflation[keep],
            self.source, self.whiteness_p[keep],
        )  # fmt: skip

    def with_sigma(self, sigma, source: str) -> NoiseModel:
        """The same colour with another level."""
        return self._replace(sigma=np.asarray(sigma, np.float64), source=source)

    def settled(self, old: NoiseModel, tol: float) -> bool:
        """True when this model is ``old`` to within ``tol`` on every output: the same
        AR orders, levels and inflations within ``tol`` relative, AR coefficients
        within ``tol`` (a refitted model that has not changed)."""

        def rel(a, b):
            return np.abs(a - b) / np.maximum(np.abs(b), 1e-300)

        return bool(
            np.array_equal(self.order, old.order)
            and np.all(rel(self.sigma, old.sigma) <= tol)
            and np.all(rel(self.inflation, old.inflation) <= tol)
            and np.all(np.abs(self.ar - old.ar) <= tol)
        )

    def filter_table(self, position: np.ndarray) -> np.ndarray:
        """``[N, S, MAX_ORDER + 1]`` whitening coefficients of each row.

        Row ``t`` at ``position[t]`` (rows since its unit's first) gets
        ``e_t = sum_k c[t, k] r_{t - k}``: the order-``p`` innovation divided by its
        std for ``position >= p``, and the innovation of the best predictor from the
        ``position`` earlier rows of its unit (Durbin–Levinson) before that, so each
        unit's first rows are transformed exactly and no row looks across units.
        """
        position = np.asarray(position, int)
        table = np.zeros((position.shape[0], self.sigma.shape[0], MAX_ORDER + 1))
        for s in range(self.sigma.shape[0]):
            rows = ar_rows(self.ar[s, : self.order[s]])
            pos = np.minimum(position, rows.shape[0] - 1)
            table[:, s, : rows.shape[1]] = rows[pos]
        return table

    def whiten(self, arr: np.ndarray, position: np.ndarray) -> np.ndarray:
        """Prewhiten and standardise ``arr [N, S, ...]`` (sensor units) along rows.

        Returns an array of the same shape whose noise part is i.i.d. with unit
        variance under the model (``sigma`` and ``inflation`` divided out).
        """
        arr = np.asarray(arr, np.float64)
        scale = self.sigma * np.sqrt(self.inflation)
        extra = (1,) * (arr.ndim - 2)
        if not self.order.any():
            return arr / scale.reshape((1, -1) + extra)
        out = _whiten_rows(self, arr, np.asarray(position, int), extra)
        out /= scale.reshape((1, -1) + extra)
        return out

    def whiten_transpose(self, arr: np.ndarray, position: np.ndarray) -> np.ndarray:
        """The transpose of :meth:`whiten` applied to ``arr [N, S, ...]`` (so that
        ``whiten_transpose(whiten(x))`` applies the noise precision ``V``)."""
        arr = np.asarray(arr, np.float64)
        scale = self.sigma * np.sqrt(self.inflation)
        extra = (1,) * (arr.ndim - 2)
        arr = arr / scale.reshape((1, -1) + extra)
        if not self.order.any():
            return arr
        table = self.filter_table(position)
        out = table[:, :, 0].reshape(table.shape[:2] + extra) * arr
        for k in range(1, MAX_ORDER + 1):
            coef = table[k:, :, k].reshape((arr.shape[0] - k, arr.shape[1]) + extra)
            if np.any(coef):
                out[:-k] += coef * arr[k:]
        return out


# cells (rows x columns) of a whitening chunk: the chunk's input and output stay in
# cache while every lag is added (a pass over the whole array per lag is memory-bound:
# 2.5-3x slower on a fleet's columns, the largest host cost of NASA FD002's diagnosis)
CHUNK_CELLS = 1 << 17


def _whiten_rows(model: NoiseModel, arr, position, extra) -> np.ndarray:
    """``e_t = sum_k c[t, k] r_{t - k}`` of :meth:`NoiseModel.filter_table` before the
    scale: each output's stationary row (a unit's rows from its ``p``-th on) applied in
    chunks of rows, then each unit's first rows again with their own rows of the table.
    Every entry takes the same products and sums in the same order as the table-wide
    form (lags in turn, leaving out a lag no row uses), so it is the same to the bit."""
    num, num_s = arr.shape[0], arr.shape[1]
    p = int(model.order.max())
    early = np.flatnonzero(position < p)
    table = model.filter_table(position[early])  # [E, S, MAX_ORDER + 1]
    stat = model.filter_table(np.array([p]))[0]  # [S, MAX_ORDER + 1]
    lags = [
        k for k in range(1, MAX_ORDER + 1)
        if (np.any(stat[:, k]) and np.any(position[k:] >= p))
        or np.any(table[early >= k, :, k])
    ]  # fmt: skip
    coef = [stat[:, k].reshape((1, num_s) + extra) for k in range(MAX_ORDER + 1)]
    out = np.empty_like(arr)
    step = max(64, CHUNK_CELLS // max(int(np.prod(arr.shape[1:])), 1))
    tmp = np.empty((min(step, num),) + arr.shape[1:])
    for a in range(0, num, step):
        b = min(a + step, num)
        np.multiply(coef[0], arr[a:b], out=out[a:b])
        for k in lags:
            lo = max(a, k)
            part = tmp[: b - lo]
            np.multiply(coef[k], arr[lo - k : b - k], out=part)
            out[lo:b] += part
    first = table[:, :, 0].reshape(table.shape[:2] + extra) * arr[early]
    for k in lags:
        ok = early >= k
        shape = (int(ok.sum()), num_s) + extra
        first[ok] += table[ok, :, k].reshape(shape) * arr[early[ok] - k]
    out[early] = first
    return out


def ar_rows(phi: np.ndarray) -> np.ndarray:
    """``[p + 1, p + 1]`` whitening rows of a stationary AR(p) with coefficients
    ``phi``: row ``i < p`` for a unit's row at position ``i`` (predictor of order
    ``i``), row ``p`` for every later row; unit marginal variance in, unit
    innovation variance out."""
    return _ar_rows(tuple(float(v) for v in np.ravel(phi))).copy()


@functools.lru_cache(maxsize=256)
def _ar_rows(phi_key: tuple) -> np.ndarray:
    phi = np.asarray(phi_key, np.float64)
    p = phi.shape[0]
    if p == 0:
        return np.ones((1, 1))
    acf = arma_acf(np.r_[1.0, -phi], [1.0], lags=p + 1)
    _, _, _, sigma, coefs = levinson_durbin(acf, nlags=p, isacov=True)
    variance = np.r_[1.0, sigma[1:]]  # prediction error variance of order 0..p
    rows = np.zeros((p + 1, p + 1))
    for i in range(p + 1):
        rows[i, 0] = 1.0
        rows[i, 1 : i + 1] = -coefs[1 : i + 1, i]
        rows[i] /= np.sqrt(variance[i])
    return rows


def positions(starts: np.ndarray, num_rows: int) -> np.ndarray:
    """``[N]`` rows since the unit's first row."""
    unit_start = np.repeat(starts[:-1], np.diff(starts))
    return np.arange(num_rows) - unit_start[:num_rows]


def by_unit(arr: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """Rows ``[N, ...]`` of the units ``starts`` -> ``[U, width, ...]``, zero past each
    unit's end (per-unit products as batched ones, no pair of rows across units)."""
    lengths = np.diff(starts)
    out = np.zeros((lengths.size, width) + arr.shape[1:])
    out[
        np.repeat(np.arange(lengths.size), lengths), positions(starts, arr.shape[0])
    ] = arr
    return out


def ljung_box_p(e: np.ndarray, lags: int = WHITENESS_LAGS) -> np.ndarray:
    """``[S]`` Ljung–Box p-values of whitened residual columns ``e [N, S]``.

    Units are concatenated: after whitening, rows of different units are
    independent, so the few pairs across a boundary are pairs of independent rows.
    The statistic of statsmodels' ``acorr_ljungbox(x, lags=[h])``, computed the same
    way to the last bit, but with only the ``h`` lags it reads: statsmodels forms
    every lag of the column (``np.correlate`` in full, O(N^2)).
    """
    n = e.shape[0]
    lags = int(min(lags, max(n // 5, 1)))
    out = np.ones(e.shape[1])
    for s in range(e.shape[1]):
        x = e[:, s]
        if not np.std(x) > 0:
            continue
        xo = x - x.mean()
        lagged = [xo[k:].dot(xo[:-k]) for k in range(1, lags + 1)]
        acov = np.array([xo.dot(xo), *lagged]) / n  # statsmodels' acovf
        sacf = acov / acov[0]
        q = n * (n + 2) * np.cumsum(sacf[1:] ** 2 / (n - np.arange(1, lags + 1)))[-1]
        out[s] = float(stats.chi2.sf(q, lags))
    return out
