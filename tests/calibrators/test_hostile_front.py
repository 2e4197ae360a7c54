"""Hostile input at the front door (issue 25): wild readings, skipped rows, memory.

A few wild rows in one unit must change no other unit's result (a robust noise and
per-row ``outlier`` flags); a skipped row reports the carried estimate or the prior,
never zeros; a calibration that keeps no row says why; units are padded in groups of
similar length, with the results of one padded array.
"""

import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.tank import MODEL, NOISE, make_frame, tank, tank_model

import jaxcal
import jaxcal.data.buckets
from jaxcal.calibrators.front.outliers import (
    describe_outliers,
    outlier_rows,
    robust_noise,
    robust_scale,
)
from jaxcal.calibrators.methods.e2e.network import E2EConfig
from jaxcal.data.buckets import bucket_units
from jaxcal.data.readers import read_dataset
from jaxcal.nets.mlp import RegressorConfig

GIVEN = dict(zip(MODEL.output_names, NOISE, strict=True))
# no input box: a negative flow reaches the model (as a model without bounds would)
OPEN = tank_model(name="tank_open", condition_range=None)


@pytest.fixture(scope="module")
def frame():
    return make_frame(num_units=4, length=40)


@pytest.fixture(scope="module")
def clean(frame):
    return jaxcal.calibrate(OPEN, frame, "ukf")


def _rows(frame, unit, times):
    """Row positions of ``unit`` at ``times`` (the frame is shuffled)."""
    return frame.index[(frame.unit == unit) & frame.time.isin(times)].to_numpy()


def _calibrate(*args, **kwargs):
    with warnings.catch_warnings():  # the console line, tested where it matters
        warnings.simplefilter("ignore", UserWarning)
        return jaxcal.calibrate(*args, **kwargs)


def _largest_change(result, clean, rows):
    """Largest change of theta on ``rows`` in units of the clean run's std."""
    change = np.abs(result.theta[rows] - clean.theta[rows]) / clean.theta_std[rows]
    return float(change.max())


def test_clean_data_flag_nothing_and_keep_their_results(frame, clean):
    assert clean.valid.all() and clean.notes == ()
    assert clean.problem.noise_source.startswith("estimated")
    screened = _calibrate(OPEN, frame, "ukf", noise=GIVEN)
    assert screened.valid.all()
    # a screening that flags nothing leaves the result bit for bit as it was
    plain = _calibrate(OPEN, frame, "ukf", noise=GIVEN, outlier_z=None)
    for field in ("theta", "theta_std", "xhat"):
        np.testing.assert_array_equal(getattr(screened, field), getattr(plain, field))


def test_one_wild_reading_changes_no_other_unit_and_is_flagged(frame, clean):
    bad = frame.copy()
    row = _rows(frame, 2, [20])[0]
    bad.loc[row, "temp"] = 1e6
    match = r"1 outlier row \(units 2 \(1\); outputs temp"
    with pytest.warns(UserWarning, match=match):
        result = jaxcal.calibrate(OPEN, bad, "ukf")
    assert result.reason[row] == "outlier" and not result.valid[row]
    assert result.num_flagged == {"outlier": 1}
    assert "outlier 1" in result.notes[-1]
    # main: the temp noise of every unit went from 0.03 to ~1e5
    np.testing.assert_allclose(
        result.problem.noise_std, clean.problem.noise_std, rtol=0.02
    )
    others = (frame.unit != 2).to_numpy()
    assert _largest_change(result, clean, others) < 0.05
    _assert_as_without(result, frame, [row])  # its own stream too


def test_impossible_operating_points_are_outliers_not_noise(frame, clean):
    bad = frame.copy()
    rows = _rows(frame, 1, range(10, 15))
    bad.loc[rows, "inflow"] = -0.5  # a negative flow, the readings of a real one
    result = _calibrate(OPEN, bad, "ukf")
    assert set(result.reason[rows]) == {"outlier"}
    assert result.valid.sum() == len(frame) - len(rows)
    # main: every output's noise estimate 4 to 250 times the clean one
    np.testing.assert_allclose(
        result.problem.noise_std, clean.problem.noise_std, rtol=0.05
    )
    _assert_as_without(result, frame, rows)


def _assert_as_without(result, frame, rows):
    """Every stream goes on as if ``rows`` had not come (within 10 % of a std;
    main: 9 stds)."""
    without = _calibrate(OPEN, frame.drop(index=rows))
    kept = np.delete(np.arange(len(frame)), rows)
    change = np.abs(result.theta[kept] - without.theta) / without.theta_std
    assert change.max() < 0.1, change.max()


@pytest.mark.parametrize("method", ["ukf", "ls"])
def test_outliers_are_flagged_against_a_given_noise(frame, method):
    bad = frame.copy()
    row = _rows(frame, 3, [25])[0]
    bad.loc[row, "level"] = -40.0
    options = {"window": 8} if method == "ls" else {}
    result = _calibrate(OPEN, bad, method, noise=GIVEN, **options)
    assert result.reason[row] == "outlier"
    assert result.valid.sum() == len(frame) - 1


def test_outlier_flags_can_be_turned_off(frame):
    bad = frame.copy()
    bad.loc[_rows(frame, 3, [25]), "level"] = -40.0
    assert _calibrate(OPEN, bad, "ukf", noise=GIVEN, outlier_z=None).valid.all()
    with pytest.raises(ValueError, match="outlier_z must be a number > 0"):
        jaxcal.calibrate(OPEN, bad, "ukf", noise=GIVEN, outlier_z=-1)


@pytest.mark.parametrize("method", ["ukf", "ls"])
def test_skipped_rows_report_the_prior_or_the_carried_estimate(frame, method):
    bad = frame.copy()
    first = _rows(frame, 0, [0, 1, 2])
    bad.loc[first, "heat"] = 80.0  # outside the model's range [0, 50]
    late, before = _rows(frame, 0, [10])[0], _rows(frame, 0, [9])[0]
    bad.loc[late, "heat"] = 80.0
    options = {"window": 8} if method == "ls" else {}
    result = _calibrate(MODEL, bad, method, noise=GIVEN, **options)
    problem = result.problem
    assert set(result.reason[first]) == {"w_out_of_range"}
    assert not result.valid[first].any()
    # main: theta = 0.0 +- 0.0 there, below the lower bound of leak (0.5)
    np.testing.assert_array_equal(
        result.theta[first], np.tile(problem.theta_prior, (3, 1))
    )
    # the UKF's prior is N(nominal, half-width); the others know the box
    half = problem.theta_half_width
    prior_std = half if method == "ukf" else half / np.sqrt(3.0)
    np.testing.assert_allclose(result.theta_std[first], np.tile(prior_std, (3, 1)))
    assert np.isnan(result.xhat[first]).all()
    assert result.reason[late] == "w_out_of_range"
    np.testing.assert_array_equal(result.theta[late], result.theta[before])
    np.testing.assert_array_equal(result.theta_std[late], result.theta_std[before])


def test_a_noise_so_small_that_every_row_is_skipped_is_an_error(frame):
    tiny = dict.fromkeys(MODEL.output_names, 1e-300)
    with pytest.raises(
        ValueError,
        match=r"calibrate: every one of the 160 rows was skipped \(state_nonfinite "
        r"160\): the model is finite .* noise std of \(level=1e-300.* too small",
    ):
        jaxcal.calibrate(MODEL, frame, "ukf", noise=tiny)


@pytest.mark.parametrize("std", [1e-300, 1e-40, 1e300])
def test_a_noise_outside_float32_is_named_with_the_dtype(frame, std):
    # main: "norm: mean must be finite and std > 0 everywhere" (1e-300 is 0 in
    # float32, 1e-40 a subnormal XLA flushes to 0, 1e300 inf)
    noise = {**GIVEN, "temp": std}
    with jax.enable_x64(False):
        with pytest.raises(
            ValueError,
            match=rf"noise: the std of temp={re.escape(f'{std:.3g}')} is outside the "
            r"range of float32.*enable float64",
        ):
            jaxcal.calibrate(MODEL, frame, "ukf", noise=noise)


def test_a_tiny_noise_that_float64_holds_is_left_to_the_filter(frame):
    result = _calibrate(MODEL, frame, "ukf", noise={**GIVEN, "temp": 1e-40})
    assert result.valid.any()


def _nan_above(w, theta):
    """The tank, NaN where the leak is above 1.5 (inside its box [0.5, 2])."""
    return jnp.where(theta[0] > 1.5, jnp.nan, 1.0) * tank(w, theta)


def _nan_at_low_flow(w, theta):
    """The tank, NaN where the inflow is below 0.8 kg/s."""
    return jnp.where(w[1] < 0.8, jnp.nan, 1.0) * tank(w, theta)


def test_a_model_nan_in_part_of_the_box_is_named_as_the_cause(frame):
    model = tank_model(_nan_above, "nan_above")
    # main: "cannot estimate the noise: fewer than two valid samples"
    with pytest.raises(
        ValueError,
        match=r"noise estimation: every one of the 160 rows was skipped.*the model "
        r"returns non-finite outputs on 160 of 160 rows \(first: row \d+, unit \d, "
        r"w=\(heat=[\d.]+, inflow=[\d.]+\), theta=\(leak=2, loss=0.1\)\)",
    ):
        jaxcal.calibrate(model, frame, "ukf")


def _nan_below_box(w, theta):
    """The tank, NaN where the loss is below -0.05: outside its box [0, 0.5] only,
    where the UKF's sigma points reach (prior 0.1 - sqrt(2) x 0.25)."""
    return jnp.where(theta[1] < -0.05, jnp.nan, 1.0) * tank(w, theta)


def test_a_model_nan_only_beyond_its_bounds_is_named_with_the_sigma_points(frame):
    model = tank_model(_nan_below_box, "nan_below_box")
    # main: "the model is finite at these rows ... a noise std ... too small"
    with pytest.raises(
        ValueError,
        match=r"calibrate: every one of the 160 rows was skipped.*non-finite outputs "
        r"on 160 of 160 rows .*theta=\(leak=1, loss=-0.25\d*\)\), outside the "
        r"parameter bounds; make the model finite there \(the UKF's sigma points",
    ):
        jaxcal.calibrate(model, frame, "ukf", noise=GIVEN)


def test_a_model_nan_on_some_rows_is_counted_and_named(frame):
    model = tank_model(_nan_at_low_flow, "nan_at_low_flow")
    low = (frame.inflow < 0.8).to_numpy()
    with pytest.warns(UserWarning, match=f"state_nonfinite {low.sum()}"):
        result = jaxcal.calibrate(model, frame, "ukf", noise=GIVEN)
    assert set(result.reason[low]) == {"state_nonfinite"}
    assert result.valid[~low].all()
    assert (
        f"the model returns non-finite outputs on {low.sum()} of {len(frame)} rows"
        in result.notes[-1]
    )


def test_robust_statistics_ignore_a_minority_of_wild_values():
    rng = np.random.default_rng(0)
    resid = rng.normal(0.0, 0.5, (2000, 2))
    resid[:20, 0] = 1e6
    np.testing.assert_allclose(robust_scale(resid), 0.5, rtol=0.1)  # the MAD
    np.testing.assert_allclose(robust_noise(resid), 0.5, rtol=0.05)
    found = outlier_rows(resid, 0.5)
    assert found.mask[:20].all() and found.mask.sum() == 20
    assert (found.worst[:20] == 0).all()
    unit = np.repeat(np.arange(4), 500)
    assert describe_outliers(found, unit, ["a", "b"]).startswith(
        "20 outlier rows (units 0 (20); outputs a (20)"
    )
    keep = np.arange(2000) >= 10
    assert outlier_rows(resid, 0.5, keep).mask.sum() == 10
    assert describe_outliers(outlier_rows(resid[20:], 0.5), unit[20:], "ab") == ""


@pytest.fixture(scope="module")
def skewed():
    """One unit of 48 rows beside short units (1 or 2 rows)."""
    lengths = [48, 1, 1, 1, 1, 2, 1, 1, 1, 1]
    frame = make_frame(num_units=1, length=sum(lengths)).sort_values("time")
    unit = np.repeat(np.arange(len(lengths)), lengths)
    start = np.repeat(np.cumsum([0, *lengths[:-1]]), lengths)
    time = np.arange(len(unit)) - start
    return frame.assign(unit=unit, time=time).reset_index(drop=True)


def test_an_ordinary_fleet_is_one_group_exactly_as_padded(frame):
    data = read_dataset(frame, MODEL)
    buckets = bucket_units(data, np.float64)
    assert len(buckets.parts) == 1
    for got, want in zip(buckets.parts[0], data.padded(np.float64), strict=True):
        np.testing.assert_array_equal(got, want)


def test_a_skewed_fleet_is_padded_in_groups_of_similar_length(skewed):
    data = read_dataset(skewed, MODEL)
    buckets = bucket_units(data, np.float64)
    # longest first: [48, 2] and eight units of 1 row, not 10 units x 48 rows
    assert [sorted(p.lengths.tolist()) for p in buckets.parts] == [[2, 48], [1] * 8]
    for part in buckets.parts:  # padding at most doubles a group's cells
        assert part.mask.size <= jaxcal.data.buckets.MAX_PADDING * part.mask.sum()
    np.testing.assert_array_equal(buckets.to_rows(buckets.from_rows(data.x)), data.x)
    np.testing.assert_array_equal(np.sort(buckets.unit_ids), np.arange(10))


def test_a_group_of_few_rows_joins_the_one_before(monkeypatch):
    """Ten units of 100 rows and twelve of one: the greedy rule leaves the last two
    one-row units a group (and a compiled program) of their own; holding 2 of the
    1,012 rows, they join the first group, whose cells stay within twice the bound."""
    lengths = [100] * 10 + [1] * 12
    frame = make_frame(num_units=1, length=sum(lengths)).sort_values("time")
    unit = np.repeat(np.arange(len(lengths)), lengths)
    time = np.arange(len(unit)) - np.repeat(np.cumsum([0, *lengths[:-1]]), lengths)
    data = read_dataset(frame.assign(unit=unit, time=time), MODEL)
    (part,) = bucket_units(data, np.float64).parts
    assert part.mask.shape == (22, 100) and part.mask.sum() == 1012
    monkeypatch.setattr(jaxcal.data.buckets, "MIN_GROUP_SHARE", 0.0)
    parts = bucket_units(data, np.float64).parts
    assert [p.mask.shape for p in parts] == [(20, 100), (2, 1)]


def test_a_skewed_fleet_calibrates_as_one_padded_array(skewed, monkeypatch):
    grouped = _calibrate(MODEL, skewed, "ukf")
    monkeypatch.setattr(jaxcal.data.buckets, "MAX_PADDING", np.inf)  # one group
    whole = _calibrate(MODEL, skewed, "ukf")
    # the same numbers up to the last bit of float64 (XLA may order a sum by the
    # batch's size); flags exactly
    np.testing.assert_allclose(
        grouped.problem.noise_std, whole.problem.noise_std, rtol=1e-12
    )
    for field in ("theta", "theta_std", "xhat"):
        np.testing.assert_allclose(
            getattr(grouped, field), getattr(whole, field), rtol=1e-12, atol=0
        )
    np.testing.assert_array_equal(grouped.reason, whole.reason)


def test_e2e_simulates_a_skewed_fleet_group_by_group(skewed):
    cfg = E2EConfig(
        hidden_sizes=(8,),
        fit=RegressorConfig(learning_rate=1e-2, batch_size=64, num_epochs=1,
                            validation_fraction=0.1, patience=1),
    )  # fmt: skip
    result = _calibrate(
        MODEL, skewed, "e2e", noise=GIVEN, e2e_config=cfg, e2e_copies=1, outlier_z=None
    )
    assert result.theta.shape == (len(skewed), 2) and np.isfinite(result.theta).all()
