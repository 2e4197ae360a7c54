"""Summaries of a normalised residual ``r_t = (x_t - F(w_t, theta_t)) / sigma``.

Per sensor: bias (mean), spread (std), RMS; autocorrelation at lags ``1..max_lag``
within units (pairs never straddle two units) and the Ljung–Box portmanteau test of
whiteness (Ljung & Box 1978), ``Q = n (n + 2) sum_k rho_k^2 / (n - k)`` against
``chi2(h)``, with the per-unit autocovariances pooled (``n`` the number of rows); the
regression of ``r`` on the ``W`` standardised operating conditions with its R^2 and
F-test; and the regression on time (cycle) (slope per 100 cycles and its t-test).
Pure numpy: this is host-side reporting, not a hot path. Rows must be sorted by unit and
time within each unit.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import stats as sps


class ResidualSummary(NamedTuple):
    """Per-sensor statistics (arrays ``[S]`` unless noted)."""

    bias: np.ndarray
    spread: np.ndarray
    rms: np.ndarray
    acf: np.ndarray  # [S, L] autocorrelation at lags 1..L
    ljung_box: np.ndarray  # Q statistic over lags 1..L
    ljung_box_p: np.ndarray
    w_coef: np.ndarray  # [S, 1 + W] intercept + W standardised conditions
    w_r2: np.ndarray
    w_p: np.ndarray  # F-test p-value of the conditions (all slopes zero)
    cycle_slope: np.ndarray  # per 100 cycles
    cycle_t: np.ndarray
    cycle_p: np.ndarray


def autocorrelation(r: np.ndarray, starts: np.ndarray, max_lag: int) -> np.ndarray:
    """Pooled within-unit autocorrelation ``[S, max_lag]`` of ``r [N, S]``.

    ``rho_k = sum_u sum_t (r_t - m)(r_{t+k} - m) / sum (r - m)^2`` with ``m`` the
    overall mean; lag pairs are taken inside each unit ``starts[u]:starts[u+1]``.
    """
    c = r - r.mean(0)
    denom = np.sum(c**2, axis=0)
    out = np.zeros((r.shape[1], max_lag))
    for k in range(1, max_lag + 1):
        num = np.zeros(r.shape[1])
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            if b - a > k:
                num += np.sum(c[a : b - k] * c[a + k : b], axis=0)
        out[:, k - 1] = np.where(denom > 0, num / np.where(denom > 0, denom, 1.0), 0.0)
    return out


def ljung_box(acf: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Ljung–Box ``Q`` and p-value for each row of ``acf [S, L]`` from ``n`` samples."""
    lags = np.arange(1, acf.shape[1] + 1)
    q = n * (n + 2) * np.sum(acf**2 / np.maximum(n - lags, 1), axis=1)
    return q, sps.chi2.sf(q, acf.shape[1])


def _regress(design: np.ndarray, y: np.ndarray):
    """OLS of every column of ``y`` on ``design`` (first column = intercept)."""
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    fitted = design @ coef
    sse = np.sum((y - fitted) ** 2, axis=0)
    sst = np.sum((y - y.mean(0)) ** 2, axis=0)
    return coef, sse, sst


def summarize_residuals(
    r: np.ndarray,
    w: np.ndarray,
    cycle: np.ndarray,
    starts: np.ndarray,
    *,
    max_lag: int = 10,
) -> ResidualSummary:
    """All summaries of a normalised residual (module docstring).

    Args:
        r: ``[N, S]`` normalised residual, rows sorted by unit then time.
        w: ``[N, W]`` operating conditions.
        cycle: ``[N]`` cycle of each row.
        starts: ``[U + 1]`` row offsets of the units.
        max_lag: autocorrelation lags (and Ljung–Box ``h``).

    Returns:
        :class:`ResidualSummary`.
    """
    n, num_s = r.shape
    if w.ndim != 2 or w.shape[0] != n or cycle.shape != (n,):
        raise ValueError(
            f"need r [N, S], w [N, W], cycle [N] with the same N; got {r.shape}, "
            f"{w.shape}, {cycle.shape}"
        )
    acf = autocorrelation(r, starts, max_lag)
    q, q_p = ljung_box(acf, n)
    w_std = w.std(0)
    varying = w_std > 0
    z = (w[:, varying] - w[:, varying].mean(0)) / w_std[varying]
    design = np.concatenate([np.ones((n, 1)), z], axis=1)
    coef_v, sse, sst = _regress(design, r)
    coef = np.zeros((1 + w.shape[1], num_s))
    coef[np.concatenate([[True], varying])] = coef_v
    k = design.shape[1] - 1
    r2 = np.where(sst > 0, 1.0 - sse / np.where(sst > 0, sst, 1.0), 0.0)
    if k > 0 and n > k + 1:
        f = (r2 / k) / np.maximum((1.0 - r2) / (n - k - 1), 1e-300)
        w_p = sps.f.sf(f, k, n - k - 1)
    else:
        w_p = np.ones(num_s)
    c = (cycle - cycle.mean()) / 100.0
    if np.any(c != 0) and n > 2:
        slope_coef, sse_c, _ = _regress(np.stack([np.ones(n), c], axis=1), r)
        se = np.sqrt(sse_c / (n - 2) / np.sum(c**2))
        slope = slope_coef[1]
        t = np.where(se > 0, slope / np.where(se > 0, se, 1.0), 0.0)
        cycle_p = 2.0 * sps.t.sf(np.abs(t), n - 2)
    else:
        slope, t, cycle_p = np.zeros(num_s), np.zeros(num_s), np.ones(num_s)
    return ResidualSummary(
        bias=r.mean(0),
        spread=r.std(0),
        rms=np.sqrt(np.mean(r**2, axis=0)),
        acf=acf,
        ljung_box=q,
        ljung_box_p=q_p,
        w_coef=coef.T,
        w_r2=r2,
        w_p=w_p,
        cycle_slope=slope,
        cycle_t=t,
        cycle_p=cycle_p,
    )


def summary_table(
    summary: ResidualSummary, sensor_names, condition_names
) -> list[dict]:
    """JSON-ready rows, one per output (``condition_names``: the ``W`` conditions)."""
    rows = []
    for s, name in enumerate(sensor_names):
        rows.append(
            {
                "sensor": name,
                "bias": float(summary.bias[s]),
                "spread": float(summary.spread[s]),
                "rms": float(summary.rms[s]),
                "acf_lag1": float(summary.acf[s, 0]),
                "ljung_box_q": float(summary.ljung_box[s]),
                "ljung_box_p": float(summary.ljung_box_p[s]),
                "w_r2": float(summary.w_r2[s]),
                "w_p": float(summary.w_p[s]),
                "w_coef": {
                    k: float(v)
                    for k, v in zip(
                        ("intercept", *condition_names),
                        summary.w_coef[s],
                        strict=True,
                    )
                },
                "cycle_slope_per_100": float(summary.cycle_slope[s]),
                "cycle_p": float(summary.cycle_p[s]),
            }
        )
    return rows
