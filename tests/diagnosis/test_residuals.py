"""Residual statistics against hand-computed values."""

import numpy as np
import pytest
from scipy import stats as sps

from jaxcal.diagnosis.residuals.summaries import (
    autocorrelation,
    ljung_box,
    summarize_residuals,
)


def test_autocorrelation_matches_hand_computation_within_units():
    # two units [1, 2, 3] and [4, 6], overall mean 3.2; lag pairs never straddle units
    r = np.array([1.0, 2.0, 3.0, 4.0, 6.0])[:, None]
    starts = np.array([0, 3, 5])
    c = r[:, 0] - 3.2
    num = c[0] * c[1] + c[1] * c[2] + c[3] * c[4]
    expected = num / np.sum(c**2)
    acf = autocorrelation(r, starts, max_lag=2)
    np.testing.assert_allclose(acf[0, 0], expected, rtol=1e-12)
    np.testing.assert_allclose(acf[0, 1], c[0] * c[2] / np.sum(c**2), rtol=1e-12)


def test_ljung_box_matches_formula():
    acf = np.array([[0.5, 0.25]])
    n = 10
    q, p = ljung_box(acf, n)
    expected = n * (n + 2) * (0.25 / 9 + 0.0625 / 8)
    np.testing.assert_allclose(q[0], expected, rtol=1e-12)
    np.testing.assert_allclose(p[0], sps.chi2.sf(expected, 2), rtol=1e-12)


def test_summary_detects_bias_w_dependence_cycle_trend_and_colour():
    rng = np.random.default_rng(0)
    n = 400
    w = np.stack(
        [
            rng.uniform(1e4, 3e4, n),
            rng.uniform(0.3, 0.7, n),
            rng.uniform(40, 80, n),
            rng.uniform(450, 500, n),
        ],
        axis=1,
    )
    cycle = np.tile(np.arange(1, 201), 2).astype(float)
    starts = np.array([0, 200, 400])
    white = rng.normal(size=n)
    mach_z = (w[:, 1] - w[:, 1].mean()) / w[:, 1].std()
    ar = np.zeros(n)
    for t in range(1, n):
        ar[t] = 0.9 * ar[t - 1] + rng.normal()
    r = np.stack([white + 2.0, 0.5 * mach_z, white + 0.01 * cycle, ar], axis=1)
    s = summarize_residuals(r, w, cycle, starts, max_lag=5)
    np.testing.assert_allclose(s.bias[0], 2.0 + white.mean(), rtol=1e-12)
    np.testing.assert_allclose(s.spread[1], np.std(0.5 * mach_z), rtol=1e-12)
    # column 1 is an exact linear function of standardised Mach
    np.testing.assert_allclose(s.w_r2[1], 1.0, atol=1e-12)
    np.testing.assert_allclose(s.w_coef[1, 2], 0.5, atol=1e-12)
    assert s.w_p[0] > 1e-3 and s.w_p[1] < 1e-10
    # slope per 100 cycles and its t-test, as scipy's linregress computes them
    ref = sps.linregress(cycle / 100.0, r[:, 2])
    assert s.cycle_slope[2] == pytest.approx(ref.slope, rel=1e-9)
    assert s.cycle_p[2] == pytest.approx(ref.pvalue, rel=1e-6) and ref.pvalue < 1e-10
    assert s.ljung_box_p[3] < 1e-10 and s.ljung_box_p[0] > 1e-3


def test_summary_rejects_bad_shapes():
    with pytest.raises(ValueError, match="w \\[N, W\\]"):
        summarize_residuals(
            np.zeros((5, 2)), np.zeros((4, 3)), np.zeros(5), np.array([0, 5])
        )
