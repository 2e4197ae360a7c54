"""The screening judged per output (issue 42): a stuck sensor is named and its
readings left out, so it costs the other outputs no row; a noise estimated from too
few rows is said, with how to give it."""

import warnings

import jax
import numpy as np
import pandas as pd
import pytest
from support.tank import NOISE, tank, tank_model

import jaxcal
from jaxcal.calibrators.front.outliers import STUCK_RUN, stuck_runs

MODEL = tank_model(condition_range=None)


def tank_frame(num_units=4, length=40, seed=0):
    rng = np.random.default_rng(seed)
    n = num_units * length
    t = np.tile(np.arange(length), num_units)
    w = np.stack([rng.uniform(5, 30, n), rng.uniform(0.5, 2.0, n)], 1)
    leak = 1.0 + 0.3 * t / length + 0.1 * np.repeat(np.arange(num_units), length)
    theta = np.stack([leak, np.full(n, 0.2)], 1)
    x = np.asarray(jax.vmap(tank)(w, theta)) + NOISE * rng.standard_normal((n, 3))
    frame = pd.DataFrame({"heat": w[:, 0], "inflow": w[:, 1]})
    for j, name in enumerate(MODEL.output_names):
        frame[name] = x[:, j]
    frame["unit"], frame["time"] = np.repeat(np.arange(num_units), length), t
    return frame


def _calibrate(frame, **options):
    """The result and its console warnings, as one string."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxcal.calibrate(MODEL, frame, "ukf", progress=False, **options)
    return result, " | ".join(str(w.message) for w in caught)


@pytest.mark.parametrize("noise", [None, {"level": 0.02, "temp": 0.02,
                                          "outflow": 0.05}])  # fmt: skip
def test_a_stuck_sensor_is_named_and_costs_the_other_outputs_no_row(noise):
    frame = tank_frame()
    rows = frame.index[(frame.unit == 1) & (frame.time >= 10)].to_numpy()
    frame.loc[rows, "outflow"] = frame.loc[rows[0], "outflow"]
    result, words = _calibrate(frame, noise=noise)
    # judged per row, 18 of these rows were skipped as outliers, level and temp too
    assert (result.reason[rows] == "ok").all() and result.valid.all()
    assert (
        result.partial[rows].all() and not result.partial[~frame.index.isin(rows)].any()
    )
    assert "stuck sensor: outflow of unit 1" in words and "30 rows" in words
    # the unit follows its level and temp as without the outflow readings at all
    dropped = frame.copy()
    dropped.loc[rows, "outflow"] = np.nan
    if noise is not None:  # (an estimated noise may differ by the left-out rows)
        without, _ = _calibrate(dropped, noise=noise)
        np.testing.assert_allclose(result.theta, without.theta, rtol=1e-5, atol=1e-6)


def test_a_quantised_output_is_not_a_stuck_sensor():
    rng = np.random.default_rng(1)
    steps = np.round(np.cumsum(rng.normal(0, 0.3, (200, 1)), 0))  # repeats often
    unit, time = np.zeros(200, int), np.arange(200)
    assert stuck_runs(steps, unit, time) == []
    smooth = rng.normal(size=(200, 2))
    smooth[50 : 50 + STUCK_RUN, 1] = 3.0
    smooth[120 : 120 + STUCK_RUN - 1, 0] = 1.0  # one short of a run
    (run,) = stuck_runs(smooth, unit, time)
    assert run.output == 1 and run.rows.tolist() == list(range(50, 50 + STUCK_RUN))
    # rows out of time order and interleaved units are put in order first
    order = rng.permutation(200)
    (run,) = stuck_runs(smooth[order], unit, time[order])
    assert sorted(time[order][run.rows].tolist()) == list(range(50, 50 + STUCK_RUN))


def test_a_noise_from_too_few_rows_is_said_with_noise_as_the_fix():
    result, words = _calibrate(tank_frame(num_units=1, length=3))
    assert "estimated from too few rows on level (2 rows" in words
    assert "give noise=" in words
    assert any("too few rows" in n for n in result.notes)
    # enough rows: no such note
    _, words = _calibrate(tank_frame(num_units=2, length=40))
    assert "too few rows" not in words
