"""The screening of one data set is done once per process (``screen_memo``): a second
method, or the same call again, reuses it; changed rows are screened again."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.calibrators.front import screen_memo


def _tank(w, theta):
    level = w[1] / theta[0]
    return jnp.stack([level, 20 + w[0] / (w[1] * (1 + theta[1])), theta[0] * level])


MODEL = jaxcal.Model.from_function(
    _tank, conditions=("heat", "inflow"),
    parameters={"leak": (1.0, 0.5, 2.0), "loss": (0.1, 0.0, 0.5)},
    outputs=("level", "temp", "outflow"),
)  # fmt: skip


def _frame(seed=0):
    rng = np.random.default_rng(seed)
    w = rng.uniform([5.0, 0.5], [30.0, 2.0], (120, 2))
    x = np.asarray(jax.vmap(_tank)(w, np.tile([1.2, 0.2], (120, 1))))
    x = x + 0.01 * rng.standard_normal(x.shape)
    x[37, 1] += 5.0  # one wild reading: the screening flags it
    columns = ("heat", "inflow", *MODEL.output_names)
    frame = pd.DataFrame(np.hstack([w, x]), columns=columns)
    frame.insert(0, "unit", np.repeat([1, 2], 60))
    return frame


def _calibrate(frame, method):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jaxcal.calibrate(MODEL, frame, method, progress=False)


@pytest.fixture(autouse=True)
def _fresh():
    screen_memo.clear()


def test_a_second_method_reuses_the_screening_and_matches_a_fresh_one():
    frame = _frame()
    ukf = _calibrate(frame, "ukf")
    before = screen_memo.counts()
    ls = _calibrate(frame, "ls")
    after = screen_memo.counts()
    assert after["reused"] == before["reused"] + 1
    assert after["screened"] == before["screened"]
    np.testing.assert_array_equal(ls.problem.noise_std, ukf.problem.noise_std)
    assert ls.noise_source == ukf.noise_source
    assert ukf.reason[37] == "outlier" and ls.reason[37] == "outlier"
    assert screen_memo.latest().outlier[37]  # what a study reads back
    # the reused screening gives what a fresh one gives, number for number
    screen_memo.clear()
    fresh = _calibrate(frame, "ls")
    np.testing.assert_array_equal(fresh.theta, ls.theta)
    np.testing.assert_array_equal(fresh.theta_std, ls.theta_std)
    np.testing.assert_array_equal(fresh.problem.noise_std, ls.problem.noise_std)


def test_changed_rows_are_screened_again():
    frame = _frame()
    first = _calibrate(frame, "ukf")
    changed = frame.copy()
    changed.loc[5, "level"] += 1e-3  # one reading
    before = screen_memo.counts()
    again = _calibrate(changed, "ukf")
    assert screen_memo.counts()["screened"] == before["screened"] + 1
    assert not np.array_equal(again.problem.noise_std, first.problem.noise_std)


def test_a_caller_cannot_change_the_kept_screening():
    frame = _frame()
    first = _calibrate(frame, "ukf")
    key, kept = next(iter(screen_memo._KEPT.items()))
    outlier = kept.outlier.copy()
    copy = screen_memo._copy(kept)
    copy.outlier[:] = ~copy.outlier
    copy.found.mask[:] = True
    np.testing.assert_array_equal(kept.outlier, outlier)
    assert not kept.found.mask.all()
    again = _calibrate(frame, "ukf")
    np.testing.assert_array_equal(again.theta, first.theta)
    assert key in screen_memo._KEPT


def test_a_screening_too_large_to_keep_is_used_not_kept(monkeypatch):
    monkeypatch.setattr(screen_memo, "MAX_BYTES", 10)  # every screening is larger
    frame = _frame()
    before = screen_memo.counts()["screened"]
    first = _calibrate(frame, "ukf")
    again = _calibrate(frame, "ukf")
    assert screen_memo.counts()["screened"] == before + 2 and not screen_memo._KEPT
    np.testing.assert_array_equal(again.theta, first.theta)
    assert screen_memo.latest() is None
