"""Fitting the noise model of :mod:`jaxcal.diagnosis.residuals.noise` to a
calibration's residual.

Estimation (:func:`fit_noise`):

1. the residual is detrended per unit (an intercept and a slope in time), so that a
   slow misfit or a unit offset is not taken for colour;
2. the pooled within-unit autocovariances give the AR(p) fits of every order by
   Durbin–Levinson (statsmodels ``levinson_durbin``); the order minimises BIC;
3. the residual is whitened with that model and the *level* (the marginal std) is
   the robust scale of differences between nearest neighbours in (conditions, time)
   within a unit, ``1.4826 MAD(e_i - e_j) / sqrt(2)``: differencing cancels what the
   model misses smoothly, and after whitening neighbouring rows are independent, so
   pairing them does not underestimate the level (raw neighbours in time are
   correlated by the colour);
4. if the whitened residual still fails the Ljung–Box test (statsmodels
   ``acorr_ljungbox``; colour AR(p) does not capture), the output's variance is
   inflated by its Bartlett long-run variance ratio (Newey & West 1987), a HAC
   fallback that keeps the tests conservative.
   A flexible fit absorbs part of the noise (:func:`projection_bias`), which is given
   back before the colour is chosen.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_banded
from statsmodels.tsa.stattools import levinson_durbin

from jaxcal.diagnosis.residuals.noise import (
    MAX_ORDER,
    WHITENESS_LAGS,
    NoiseModel,
    by_unit,
    ljung_box_p,
    positions,
)

HAC_ALPHA = 0.01  # a whitened residual failing Ljung–Box at this level is inflated
CORRECTION_ROUNDS = 4  # fixed-point steps of the fit's absorption correction
BIAS_ROWS = 8192  # rows of units taken together by projection_bias (memory)


def detrend(resid: np.ndarray, data) -> np.ndarray:
    """``resid [N, S]`` minus its per-unit intercept and slope in time (a slow misfit
    or a unit's offset is not taken for colour)."""
    out = np.empty_like(resid)
    for u in range(data.num_units):
        sl = slice(data.starts[u], data.starts[u + 1])
        design = np.stack([np.ones(sl.stop - sl.start), data.tau[sl]], axis=1)
        coef = np.linalg.lstsq(design, resid[sl], rcond=None)[0]
        out[sl] = resid[sl] - design @ coef
    return out


def pair_counts(starts: np.ndarray, max_lag: int) -> np.ndarray:
    """``[max_lag + 1]`` row pairs at each lag within units."""
    lengths = np.diff(starts)
    return np.array([np.maximum(lengths - k, 0).sum() for k in range(max_lag + 1)])


def pooled_acov(u: np.ndarray, starts: np.ndarray, max_lag: int) -> np.ndarray:
    """``[S, max_lag + 1]`` within-unit autocovariances of ``u [N, S]`` pooled over
    the units, each lag's sum over its own number of pairs (pairs never straddle two
    units)."""
    out = np.zeros((u.shape[1], max_lag + 1))
    n = u.shape[0]
    out[:, 0] = np.sum(u**2, axis=0)
    pos = positions(starts, n)
    for k in range(1, max_lag + 1):
        same = pos[k:] >= k  # row t and t - k in one unit
        out[:, k] = np.sum(u[k:][same] * u[:-k][same], axis=0)
    return out / np.maximum(pair_counts(starts, max_lag), 1)


def select_order(acov: np.ndarray, n: int, max_order: int) -> tuple[int, np.ndarray]:
    """AR order by BIC ``n ln v_p + p ln n`` and its coefficients (Durbin–Levinson
    on one output's autocovariances ``acov [L + 1]``)."""
    if acov[0] <= 0 or max_order == 0:
        return 0, np.zeros(0)
    acf = acov[: max_order + 1] / acov[0]
    _, _, pacf, sigma, coefs = levinson_durbin(acf, nlags=max_order, isacov=True)
    variance = np.r_[1.0, sigma[1:]]
    best, best_bic = 0, 0.0
    for p in range(1, max_order + 1):
        if not 0 < variance[p] <= 1 or not np.all(np.abs(pacf[1 : p + 1]) < 1):
            break
        bic = n * np.log(variance[p]) + p * np.log(n)
        if bic < best_bic:
            best, best_bic = p, bic
    return best, np.asarray(coefs[1 : best + 1, best]) if best else np.zeros(0)


def nn_scale(e: np.ndarray, data, *, block: int = 1024) -> np.ndarray:
    """``[S]`` robust scale of nearest-neighbour differences of ``e [N, S]`` within
    units, neighbours in standardised (conditions, time): ``1.4826 MAD / sqrt(2)``."""
    w_std = data.w.std(0)
    feats = [
        (data.w[:, j] - data.w[:, j].mean()) / w_std[j]
        for j in range(data.w.shape[1])
        if w_std[j] > 0
    ]
    span = np.maximum(
        np.maximum.reduceat(data.cycle, data.starts[:-1])
        - np.minimum.reduceat(data.cycle, data.starts[:-1]),
        1.0,
    )
    feats.append(data.cycle / span[data.unit])
    z = np.stack(feats, axis=1)
    diffs = []
    for u in range(data.num_units):
        a, b = data.starts[u], data.starts[u + 1]
        if b - a < 2:
            continue
        zu, eu = z[a:b], e[a:b]
        for c in range(0, b - a, block):
            d2 = ((zu[c : c + block, None, :] - zu[None, :, :]) ** 2).sum(-1)
            d2[np.arange(d2.shape[0]), c + np.arange(d2.shape[0])] = np.inf
            diffs.append(eu[c : c + block] - eu[np.argmin(d2, axis=1)])
    if not diffs:
        raise ValueError("noise estimation needs a unit with at least two rows")
    d = np.concatenate(diffs, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(2.0)


def lrv_factor(acov: np.ndarray, n: int) -> np.ndarray:
    """``[S]`` Bartlett-kernel long-run variance over variance, bandwidth
    ``floor(4 (n / 100)^(2/9))`` (Newey & West 1994), at least 1."""
    lags = min(int(4 * (n / 100.0) ** (2.0 / 9.0)), acov.shape[1] - 1)
    weights = 1.0 - np.arange(1, lags + 1) / (lags + 1.0)
    rho = acov[:, 1 : lags + 1] / np.maximum(acov[:, :1], 1e-300)
    return np.maximum(1.0 + 2.0 * rho @ weights, 1.0)


def projection_bias(
    data, cols: np.ndarray, fit: NoiseModel, noise: NoiseModel, max_lag: int
) -> np.ndarray:
    """``[S, max_lag + 1]`` bias of the pooled autocovariances of a fit's residual.

    A fit absorbs part of the noise. With the fit's columns ``D`` (its per-unit
    coefficients, here with each unit's intercept and slope of the detrending), the
    precision ``V`` it weighted the rows with (the prewhitening of ``fit``) and the
    noise covariance ``Sigma`` (of ``noise``), the residual ``r = M e`` with
    ``M = I - P``, ``P = D (D^T V D)^-1 D^T V``, has ``E[r r^T] = M Sigma M^T``, so its
    sample autocovariance at lag ``k`` is off by
    ``tr(J_k (P Sigma P^T - P Sigma - Sigma P^T)) / N_k`` (``J_k`` picks an output's
    ``N_k`` pairs at lag ``k`` within a unit), computed per unit and output block: with
    ``A = D^T V D``, ``C_s = Sigma_s V_s D_s`` and ``G = sum_t D_t^T V_t C_t``, it is
    ``tr(A^-1 G A^-1 D_s^T J D_s) - 2 tr(A^-1 C_s^T J D_s)``. Flexible per-unit splines
    on short units absorb much of a coloured noise's low frequencies: uncorrected,
    colour and level come out low (the restricted-likelihood bias; Harville 1977).
    """
    n, num_s = cols.shape[0], cols.shape[1]
    pos = positions(data.starts, n)
    lengths = np.diff(data.starts)
    out = np.zeros((num_s, max_lag + 1))
    eye = np.eye(num_s)
    coloured = np.flatnonzero(noise.order > 0)
    # units in groups of about BIAS_ROWS rows, each on a [units, rows, S, q] layout
    # (zero past each unit's end, so no product pairs rows of two units)
    group = np.cumsum(lengths) // BIAS_ROWS
    for g in np.unique(group):
        units = np.flatnonzero(group == g)
        a, b = data.starts[units[0]], data.starts[units[-1] + 1]
        tau = data.tau[a:b, None, None]
        trend = np.concatenate(
            [np.broadcast_to(eye, (b - a,) + eye.shape), eye * tau], 2
        )
        rows = np.concatenate([cols[a:b], trend], axis=2)  # [n, S, q]
        vrows = fit.whiten_transpose(fit.whiten(rows, pos[a:b]), pos[a:b])  # V D
        m, local = int(lengths[units].max()), data.starts[units[0] : units[-1] + 2] - a
        d, vd = by_unit(rows, local, m), by_unit(vrows, local, m)
        # C_s = Sigma_s V_s D_s, Sigma_s = sigma_s^2 R_s with R_s = L_s^-1 L_s^-T (L_s
        # the AR whitening of the noise's colour, lower triangular with p bands: its
        # rows depend on the position alone, so one m x m band serves every unit of
        # the group; zero rows past a unit's end stay zero)
        c = vd * (noise.sigma**2)[:, None]
        inside = np.arange(m) < lengths[units][:, None]  # not past the unit's end
        table = noise.filter_table(np.arange(m))  # [m, S, MAX_ORDER + 1]
        for s in coloured:
            p = int(noise.order[s])
            lower = np.zeros((p + 1, m))  # L[j + k, j] at [k, j]
            upper = np.zeros((p + 1, m))  # L^T[j - k, j] = L[j, j - k] at [p - k, j]
            for k in range(p + 1):
                lower[k, : m - k] = table[k:, s, k]
                upper[p - k] = table[:, s, k]
            rhs = vd[:, :, s].transpose(1, 0, 2).reshape(m, -1)
            half = solve_banded((0, p), upper, rhs, check_finite=False)
            full = solve_banded((p, 0), lower, half, check_finite=False)
            full = full.reshape(m, units.size, -1).transpose(1, 0, 2)
            c[:, :, s] = noise.sigma[s] ** 2 * full * inside[:, :, None]
        flat = (units.size, -1, d.shape[3])  # batched BLAS: [u, t s, q]
        dt = d.reshape(flat).transpose(0, 2, 1)
        a_inv = np.linalg.pinv(dt @ vd.reshape(flat))
        agai = a_inv @ (vd.reshape(flat).transpose(0, 2, 1) @ c.reshape(flat)) @ a_inv
        # tr(A^-1 G A^-1 sym(D_s^T J D_s)) and tr(A^-1 C_s^T J D_s) as sums over the
        # lag's row pairs of d_{t+k} . (d_t M): O(m S q) a lag, not O(m S q^2)
        d_agai = (d.reshape(flat) @ agai).reshape(d.shape)
        d_ainv = (d.reshape(flat) @ a_inv).reshape(d.shape)
        for k in range(min(max_lag, m - 1) + 1):
            late, early = slice(k, m), slice(0, m - k)
            dd = 0.5 * (
                np.einsum("utsi,utsi->s", d[:, late], d_agai[:, early])
                + np.einsum("utsi,utsi->s", d[:, early], d_agai[:, late])
            )
            cd = np.einsum("utsi,utsi->s", c[:, late], d_ainv[:, early]) + np.einsum(
                "utsi,utsi->s", c[:, early], d_ainv[:, late]
            )
            out[:, k] += dd - cd
    return out / np.maximum(pair_counts(data.starts, max_lag), 1)


def _acf(acov: np.ndarray) -> np.ndarray:
    """Autocorrelations of autocovariances ``[S, L + 1]``."""
    return acov / np.maximum(acov[:, :1], 1e-300)


def _fit_colour(acov: np.ndarray, n: int, max_order: int) -> NoiseModel:
    """A unit-level noise model with the AR colour of ``acov [S, L + 1]``."""
    num_s = acov.shape[0]
    ar = np.zeros((num_s, MAX_ORDER))
    order = np.zeros(num_s, int)
    for s in range(num_s):
        p, phi = select_order(acov[s], n, max_order)
        order[s], ar[s, :p] = p, phi
    return NoiseModel(
        np.ones(num_s), ar, order, np.ones(num_s), "estimated", np.full(num_s, np.nan)
    )


def fit_noise(
    resid: np.ndarray,
    data,
    *,
    sigma: np.ndarray | None = None,
    max_order: int = MAX_ORDER,
    cols: np.ndarray | None = None,
    fit: NoiseModel | None = None,
) -> NoiseModel:
    """The noise model of a calibration's residual (module docstring).

    Args:
        resid: ``[N, S]`` residual ``x - xhat`` in output units, rows sorted by unit
            and time (:class:`~jaxcal.diagnosis.data.prepare.LoopData` order).
        data: the rows (``w``, ``tau``, ``unit``, ``starts``, ``cycle``).
        sigma: a known marginal std ``[S]`` (only the colour is estimated).
        max_order: highest AR order (0: white noise and no HAC inflation either:
            the rows taken as independent).
        cols: ``[N, S, L]`` the fit's per-unit columns (output units, not
            whitened): the autocovariances are then corrected for what the fit
            absorbed (:func:`projection_bias`, solved for the colour it implies).
        fit: the noise model the fit weighted its rows with (default: white at the
            residual's own std, ordinary least squares).

    Returns:
        :class:`NoiseModel` (``source`` ``given`` when ``sigma`` is given).
    """
    if not 0 <= max_order <= MAX_ORDER:
        raise ValueError(f"max_order must be in 0..{MAX_ORDER}, got {max_order}")
    u = detrend(resid, data)
    n, num_s = u.shape
    lags = max(max_order, WHITENESS_LAGS)
    sample = pooled_acov(u, data.starts, lags)
    pos = positions(data.starts, n)
    if fit is None:
        fit = NoiseModel.white(np.maximum(np.std(resid, axis=0), 1e-300), "fit")

    def model_of(acov):
        """The noise model of corrected autocovariances ``acov [S, L + 1]``."""
        model = _fit_colour(acov, n, max_order)
        e = model.whiten(resid, pos)  # output units, marginal scale
        if sigma is None:  # differences see what the fit absorbed too: scaled back
            absorbed = sample[:, 0] / np.maximum(acov[:, 0], 1e-300)
            level = nn_scale(e, data) / np.sqrt(np.clip(absorbed, 0.25, 1.0))
        else:
            level = np.asarray(sigma, np.float64)
        level = np.where(level > 0, level, np.maximum(np.std(resid, axis=0), 1e-300))
        return model._replace(sigma=level, source="estimated" if sigma is None
                              else "given")  # fmt: skip

    def corrected(model):
        """The sample autocovariances with what the fit absorbed (under ``model``)
        given back."""
        out = sample.copy()
        out[:, : max_order + 1] -= projection_bias(data, cols, fit, model, max_order)
        return out

    acov = sample
    if cols is not None:
        # x = F(x): the correction under the colour it implies, by fixed-point steps
        # from the uncorrected estimate (each closer; under-correcting, never
        # overshooting, when the fit absorbs much: ill-conditioned extrapolation
        # would amplify the sampling noise)
        for _ in range(CORRECTION_ROUNDS):
            acov = corrected(model_of(acov))
        # What a fit absorbs lowers a residual's variance and its low-lag
        # correlations; a correction that does the opposite for an output (sampling
        # noise, amplified where the fit absorbs most of it) is not trusted.
        rho, rho_raw = _acf(acov), _acf(sample)
        bad = (acov[:, 0] < sample[:, 0]) | (rho[:, 1] < rho_raw[:, 1])
        acov[bad] = sample[bad]
    model = model_of(acov)
    white_u = model.whiten(u, pos)
    p_value = ljung_box_p(white_u)
    inflation = np.ones(num_s)
    bad = p_value < HAC_ALPHA
    if bad.any() and max_order > 0:  # max_order 0: rows independent, as assumed
        inflation[bad] = lrv_factor(pooled_acov(white_u, data.starts, lags), n)[bad]
    return model._replace(inflation=inflation, whiteness_p=p_value)


def quantised(data, sigma: np.ndarray) -> dict[str, str]:
    """Outputs whose rounding step dominates the noise level (or whose level is 0)."""
    reasons = {}
    for j, s in enumerate(data.sensor_names):
        values = np.unique(data.x[:, j])
        step = np.diff(values).min() if values.size > 1 else 0.0
        if not sigma[j] > 0:
            reasons[s] = "noise estimate is zero (constant or rounded readings)"
        elif step / np.sqrt(12.0) > 0.5 * sigma[j]:
            reasons[s] = (
                f"quantised: rounding step {step:.3g} dominates the noise "
                f"estimate {sigma[j]:.3g}"
            )
    return reasons
