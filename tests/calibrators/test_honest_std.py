"""Issue 42, honest uncertainty: a coloured noise widens the std, a late shift in the
innovations withholds it (``jaxcal/calibrators/uncertainty/misfit_check.py``), on
synthetic
innovations and on the newcomer's reactor (``tests/support/reactor.py``)."""

import warnings

import numpy as np
import pytest

import jaxcal
from jaxcal.calibrators.uncertainty.misfit_check import (
    SHIFTED,
    WIDEN_FROM,
    ar_long_run_ratio,
    colour_rows,
    shift_statistic,
)
from tests.support.reactor import MODEL, THETA, small_fleet

Z90 = 1.6448536269514722


def _ar1(rng, n, phi):
    out = np.zeros(n)
    shocks = rng.standard_normal(n) * np.sqrt(1 - phi**2)
    for t in range(1, n):
        out[t] = phi * out[t - 1] + shocks[t]
    return out


def test_the_ar_ratio_is_one_for_white_noise_and_the_ar1_value_for_ar1():
    rng = np.random.default_rng(0)
    assert abs(ar_long_run_ratio(rng.standard_normal(2000)) - 1.0) < 0.1
    # AR(1) of 0.8: (1 + 0.8) / (1 - 0.8) = 9 (the Bartlett estimate reads less)
    assert 9 * 0.75 < ar_long_run_ratio(_ar1(rng, 2000, 0.8)) < 9 * 1.25


def test_a_late_shift_is_seen_and_a_stationary_colour_is_not():
    rng = np.random.default_rng(1)
    white = rng.standard_normal(450)
    assert shift_statistic(white) < SHIFTED
    assert shift_statistic(_ar1(rng, 450, 0.8)) < SHIFTED  # scaled by its colour
    shifted = white.copy()
    shifted[270:300] += 1.0  # a transient the filter then absorbs: 30 rows of 1 std
    assert shift_statistic(shifted) > SHIFTED


def test_colour_rows_widens_the_coloured_unit_and_flags_the_shifted_one():
    rng = np.random.default_rng(2)
    n = 400
    unit = np.repeat([1, 2, 3], n)
    time = np.tile(np.arange(n), 3)
    z = rng.standard_normal((3 * n, 2))
    z[unit == 2, 0] = _ar1(rng, n, 0.6)  # (1.6 / 0.4 = 4: widened by about 2)
    z[(unit == 3) & (time >= 250) & (time < 290), 1] += 1.5  # a late shift
    order = rng.permutation(3 * n)
    colour = colour_rows(unit[order], time[order], z[order], np.ones(3 * n, bool))
    np.testing.assert_array_equal(colour.misfit, unit[order] == 3)
    widen = colour.widen[unit[order] == 2]
    assert np.all(widen == widen[0]) and 1.6 < widen[0] < 2.6
    assert np.all(colour.widen[unit[order] != 2] == 1.0)
    assert np.sqrt(WIDEN_FROM) < widen[0]


def _coverage(result, frame):
    truth = frame[list(THETA)].to_numpy()
    keep = result.valid & (frame["time"].to_numpy() >= 30)
    keep &= np.isfinite(result.theta_std).all(axis=1)
    inside = np.abs(result.theta - truth) <= Z90 * result.theta_std
    return inside[keep].mean()


@pytest.fixture(scope="module")
def runs():
    def run(**scenario):
        frame = small_fleet(0, **scenario)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            result = jaxcal.calibrate(MODEL, frame, "ukf", theta=THETA)
        return frame, result

    return run


def test_the_reactor_with_ar_noise_keeps_a_widened_std_that_covers(runs):
    frame, result = runs(phi=0.8)
    assert not result.misfit.any()
    assert any("coloured" in n and "widened" in n for n in result.notes)
    assert 0.85 <= _coverage(result, frame) <= 0.97  # unwidened: about 0.6


def test_the_reactor_with_a_late_sensor_bias_withholds_those_units_std(runs):
    frame, result = runs(bias=1.5, bias_units=(1, 3), bias_from=180)
    flagged = np.unique(result.unit[result.misfit])
    np.testing.assert_array_equal(flagged, [1, 3])
    assert np.isnan(result.theta_std[result.misfit]).all()
    assert np.isfinite(result.theta_std[~result.misfit]).all()
    assert any("shifted from some row on" in n for n in result.notes)


def test_e2e_stays_in_the_box_with_a_held_out_std():
    from jaxcal.calibrators.methods.e2e.network import E2EConfig
    from jaxcal.nets.mlp import RegressorConfig
    from tests.support.tank import MODEL as TANK
    from tests.support.tank import NOISE as TANK_NOISE
    from tests.support.tank import make_frame

    frame = make_frame(num_units=3, length=80, seed=3)
    cfg = E2EConfig(
        hidden_sizes=(32, 32),
        fit=RegressorConfig(learning_rate=3e-3, batch_size=128, num_epochs=30,
                            validation_fraction=0.1, patience=10),
    )  # fmt: skip
    noise = dict(zip(TANK.output_names, TANK_NOISE, strict=True))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        result = jaxcal.calibrate(
            TANK, frame, "e2e", noise=noise, e2e_config=cfg,
            e2e_copies=2,
        )  # fmt: skip
    assert np.all((result.theta >= [0.5, 0.0]) & (result.theta <= [2.0, 0.5]))
    std = result.theta_std[result.valid]
    assert np.all(np.isfinite(std) & (std > 0))
    # nothing dishonest in it: about 90 % of the (white-noise) rows inside
    truth = frame[["leak", "loss"]].to_numpy()
    inside = np.abs(result.theta - truth) <= Z90 * result.theta_std
    assert 0.75 <= inside[result.valid].mean() <= 1.0
