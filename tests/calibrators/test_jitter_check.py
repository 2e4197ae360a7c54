"""A reported theta std is never below the estimate's own row-to-row scatter
(``jaxcal/calibrators/uncertainty/jitter_check.py``).

Given a noise 40x too small on ``dp_hot``, the heat exchanger's UKF follows that
output's noise through ``dp_coeff`` with a std about 50x too small (as it did with
the noise estimated from the post-fit residual, before the innovation estimator):
2 % of the rows inside its 90 % interval. The check floors such a std at the scatter
and leaves a consistent one exactly as it was.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

import jaxcal
from jaxcal.calibrators.uncertainty.jitter_check import jitter_floor

sys.path.insert(
    0, str(Path(__file__).resolve().parents[2] / "examples" / "heat_exchanger")
)
from make_data import NOISE, make_fleet  # noqa: E402

Z90 = 1.6448536269514722


def _units(num_units=3, length=300, seed=0):
    """``(unit, time, truth)``: slowly drifting truth, rows shuffled."""
    rng = np.random.default_rng(seed)
    unit = np.repeat(np.arange(1, num_units + 1), length)
    time = np.tile(np.arange(length), num_units)
    truth = np.stack([0.001 * time, np.full(time.shape, 2.0)], 1)
    order = rng.permutation(len(unit))
    return unit[order], time[order], truth[order], rng


def test_a_std_far_below_the_scatter_is_raised_to_it():
    unit, time, truth, rng = _units()
    theta = truth + 0.1 * rng.standard_normal(truth.shape)  # errors white, std 0.1
    std = np.full(theta.shape, 0.002)  # 50x too small
    valid = np.ones(len(unit), bool)
    checked, factor = jitter_floor(unit, time, theta, std, valid)
    assert np.all(checked >= std)
    np.testing.assert_allclose(np.median(checked, 0), 0.1, rtol=0.15)
    assert np.all(factor > 30)
    inside = np.abs(theta - truth) <= Z90 * checked
    assert 0.85 <= inside.mean() <= 0.95


def test_a_consistent_std_is_left_exactly_and_a_step_does_not_count():
    unit, time, truth, rng = _units(seed=1)
    # a filter's errors: correlated from row to row (AR(1), 0.8), std 0.1
    err = np.zeros(truth.shape)
    innovation = rng.standard_normal(truth.shape) * 0.1 * np.sqrt(1 - 0.8**2)
    by_time = np.argsort(time, kind="stable")
    for u in np.unique(unit):
        rows = by_time[unit[by_time] == u]
        for k in range(1, len(rows)):
            err[rows[k]] = 0.8 * err[rows[k - 1]] + innovation[rows[k]]
    truth = truth + np.where(time >= 150, 5.0, 0.0)[:, None]  # a step fault
    std = np.full(truth.shape, 0.1)
    valid = np.ones(len(unit), bool)
    checked, factor = jitter_floor(unit, time, truth + err, std, valid)
    np.testing.assert_array_equal(checked, std)
    np.testing.assert_array_equal(factor, 1.0)


def test_skipped_rows_and_a_short_unit_are_left_alone():
    unit, time, truth, rng = _units(num_units=2, length=40)
    theta = truth + 0.1 * rng.standard_normal(truth.shape)
    std = np.full(theta.shape, 0.001)
    valid = unit == 1  # unit 2 used no row: nothing to judge it by
    checked, _ = jitter_floor(unit, time, theta, std, valid)
    assert np.all(checked[unit == 1] > 0.05)
    np.testing.assert_array_equal(checked[unit == 2], 0.001)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_given_noise_far_too_small_leaves_the_ukf_honest_all_the_same():
    fleet = make_fleet(0)
    test = fleet[fleet.unit.isin([10, 11])].reset_index(drop=True)
    names = ["fouling", "dp_coeff"]
    truth = test[names].to_numpy()

    def covered(result):
        keep = result.valid & (test.time.to_numpy() >= 24)
        err = np.abs(result.theta - truth)[keep]
        return (err <= Z90 * result.theta_std[keep]).mean(0)

    small = {**NOISE, "dp_hot": NOISE["dp_hot"] / 40}  # the filter follows dp_hot
    raised = jaxcal.calibrate("heat_exchanger", test, "ukf", theta=names, noise=small)
    assert covered(raised)[1] > 0.8  # 0.02 without the check
    assert any("row-to-row scatter on dp_coeff" in n for n in raised.notes)
    given = jaxcal.calibrate("heat_exchanger", test, "ukf", theta=names, noise=NOISE)
    assert not any("row-to-row scatter" in n for n in given.notes)  # consistent
    assert 0.85 <= covered(given).min() <= 0.97
