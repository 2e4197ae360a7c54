"""The prognosis core on a toy fleet whose end of life is known, its errors, the
scores, and ``prognose`` end to end on the heat exchanger.

The toy fleet (:func:`_toy_fleet`): each unit's ``health`` falls as
``c - a (exp(t / tau) - 1)`` plus AR(1) noise and fails when the trend reaches
:data:`LIMIT`; a training unit's last row is exactly that crossing, a test unit is cut
at a random age and its true RUL is the rest. A second parameter ``noise`` is a
per-unit level plus white noise (its end values are scattered: it must not decide).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from jaxcal.prognosis import (
    PrognosisConfig,
    degradation,
    from_arrays,
    phm08_score,
    predict,
    prognose,
    prognose_trajectories,
    read_truth,
    score,
)

LIMIT = 0.6  # the toy's failure boundary on `health`
NAMES = ("health", "noise")
# one trend and noise scale: the held-out check scores one choice, faster
FAST = PrognosisConfig(samples=300, trend="poly3", noise_scale=1.0)


def _toy_fleet(seed: int, num_units: int, *, cut: bool, wear: bool = False):
    """Per-row ``(unit, time, theta [N, 2])`` and each unit's true RUL (cut units).

    ``wear``: the second parameter rises linearly from 0 to 1 over the life instead
    of being noise (for a declared boundary it reaches before `health` fails).
    """
    rng = np.random.default_rng(seed)
    unit, time, theta, truth = [], [], [], []
    for u in range(num_units):
        life = int(rng.integers(120, 201))
        tau = rng.uniform(60.0, 100.0)
        c = rng.normal(1.0, 0.02)
        t = np.arange(1.0, life + 1.0)
        # a chosen so that the trend reaches LIMIT exactly at the last row, t = life
        trend = c - (c - LIMIT) * np.expm1(t / tau) / np.expm1(life / tau)
        ar = np.zeros(life)
        for k in range(1, life):  # AR(1): the calibrators' estimates are correlated
            ar[k] = 0.7 * ar[k - 1] + rng.normal(0.0, 0.004)
        second = (
            t / life + rng.normal(0.0, 0.005, life)
            if wear
            else rng.normal(0.5, 0.1) + rng.normal(0.0, 0.02, life)
        )
        rows = life
        if cut:
            rows = int(rng.integers(int(0.3 * life), int(0.9 * life)))
            truth.append(life - t[rows - 1])
        unit.append(np.full(rows, u + 1))
        time.append(t[:rows])
        theta.append(np.stack([trend + ar, second], 1)[:rows])
    rows = (np.concatenate(unit), np.concatenate(time), np.concatenate(theta))
    return rows, np.array(truth)


@pytest.fixture(scope="module")
def toy():
    """15 run-to-failure units and 60 cut ones, predicted with the noise scale the
    held-out check chooses (the trend fixed to poly3, to keep it fast) and the learned
    boundary."""
    train_rows, _ = _toy_fleet(0, 15, cut=False)
    test_rows, truth = _toy_fleet(1, 60, cut=True)
    train = from_arrays(*train_rows, NAMES, label="train")
    test = from_arrays(*test_rows, NAMES, label="test")
    result = prognose_trajectories(
        train, test, config=PrognosisConfig(samples=300, trend="poly3")
    )
    return train, test, truth, result


def test_predicted_rul_is_close_to_the_truth(toy):
    _, test, truth, result = toy
    pred = result.prediction
    np.testing.assert_array_equal(pred.unit, test.unit)
    np.testing.assert_allclose(pred.now, test.now)
    rmse = np.sqrt(np.mean((pred.rul - truth) ** 2))
    assert truth.std() > 20.0  # the cut ages make the truths spread
    assert rmse < 0.4 * truth.std(), (rmse, truth.std())
    assert abs(np.mean(pred.rul - truth)) < 5.0  # no systematic bias
    assert np.all(pred.rul_low <= pred.rul) and np.all(pred.rul <= pred.rul_high)


def test_interval_coverage_is_near_nominal(toy):
    _, _, truth, result = toy
    pred = result.prediction
    s = score(pred.rul, pred.rul_low, pred.rul_high, truth)
    assert s["units"] == 60
    assert 0.78 <= s["coverage"] <= 0.99, s
    # honest, not vacuous: the intervals are narrower than the spread of the truths
    assert s["mean_width"] < 1.5 * truth.std(), s
    check = result.noise_check
    assert check["trends"] == ["poly3"] and check["cases"] == 30
    assert check["noise_scale"] in check["scales"]
    j = check["scales"].index(check["noise_scale"])
    assert check["crps"][0][j] == min(check["crps"][0])  # the lowest held-out CRPS


def test_learned_boundary_is_where_units_fail(toy):
    _, _, _, result = toy
    model = result.model
    health = model.names.index("health")
    assert abs(model.boundary[health] - LIMIT) < 0.02, model.boundary
    assert model.direction[health] == -1.0  # health falls to its boundary
    assert model.boundary_std[health] < 0.02
    assert not model.declared.any()
    assert model.lives.min() >= 120 and model.lives.max() <= 200


def test_only_the_consistent_parameter_decides(toy):
    _, _, _, result = toy
    model = result.model
    np.testing.assert_array_equal(model.decides, [True, False])
    assert model.tightness[0] < 0.1  # health: ends tight around LIMIT
    assert model.tightness[1] > model.tightness[0] * 10  # noise: scattered ends
    assert set(result.prediction.driver) == {"health"}
    assert np.all(result.prediction.driver_share == 1.0)  # noise never decides


def test_a_declared_boundary_overrides_and_always_decides(toy):
    train, test, _, result = toy
    model = degradation.fit(train, boundary={"noise": 2.0, "health": LIMIT + 0.1})
    np.testing.assert_array_equal(model.decides, [True, True])
    np.testing.assert_array_equal(model.declared, [True, True])
    np.testing.assert_allclose(model.boundary, [LIMIT + 0.1, 2.0])
    np.testing.assert_array_equal(model.boundary_std, [0.0, 0.0])
    assert np.isnan(model.tightness).all()
    # once a limit is declared, only declared limits decide: a learned one that happens
    # to be tight does not end lives the user has said end otherwise
    only = degradation.fit(train, boundary={"noise": 2.0})
    np.testing.assert_array_equal(only.decides, [False, True])
    # a higher limit on a falling parameter is reached earlier: shorter lives
    earlier = prognose_trajectories(
        train, test, {"health": LIMIT + 0.1}, dataclasses.replace(FAST, seed=3)
    )
    assert np.all(earlier.prediction.rul < result.prediction.rul)
    # the training units end near LIMIT, not at the declared LIMIT + 0.1: said so
    assert any("not at the declared 0.7" in n for n in earlier.notes), earlier.notes
    assert not any("not at the declared" in n for n in result.notes)
    assert np.median(result.prediction.rul - earlier.prediction.rul) > 5.0


def test_the_driver_is_the_parameter_whose_boundary_comes_first():
    """`wear` rises 0 -> 1 over each life; declared at 0.5 it is reached near mid
    life, long before `health` fails, so it drives and sets the RUL."""
    train_rows, _ = _toy_fleet(2, 12, cut=False, wear=True)
    test_rows, truth = _toy_fleet(3, 12, cut=True, wear=True)
    train = from_arrays(*train_rows, NAMES)
    test = from_arrays(*test_rows, NAMES)
    result = prognose_trajectories(train, test, {"noise": 0.5}, FAST)
    pred = result.prediction
    early = pred.now < 0.4 * (pred.now + truth)  # cut before the wear limit
    assert early.sum() >= 2
    assert all(pred.driver[i] == "noise" for i in np.flatnonzero(early))
    life = pred.now + truth
    wear_rul = 0.5 * life - pred.now  # the wear limit is reached at half life
    np.testing.assert_allclose(pred.rul[early], wear_rul[early], atol=12.0)


def test_rows_are_grouped_by_unit_and_sorted_by_time_in_any_order():
    unit = np.array(["b", "a", "b", "a", "b", "a"])
    time = np.array([3.0, 2.0, 1.0, 1.0, 2.0, 3.0])
    theta = np.column_stack([time * 10 + (unit == "b"), time])
    traj = from_arrays(unit, time, theta, NAMES)
    assert traj.unit.tolist() == ["b", "a"]  # first-appearance order
    np.testing.assert_array_equal(traj.time, [[1, 2, 3], [1, 2, 3]])
    np.testing.assert_array_equal(traj.theta[..., 0], [[11, 21, 31], [10, 20, 30]])


def test_a_unit_to_predict_may_have_a_single_row(toy):
    """Its posterior is the fleet's prior moved by one point: a RUL, a wide interval."""
    train, test, _, result = toy
    one = from_arrays([7], [5.0], [[0.99, 0.0]], NAMES, min_rows=1)
    pred = predict(result.model, one, jax.random.PRNGKey(0), num_samples=300)
    assert np.isfinite(pred.rul[0]) and pred.rul_low[0] < pred.rul[0] < pred.rul_high[0]
    lives = result.model.lives
    assert lives.min() - 5 - 30 < pred.rul[0] < lives.max()  # within the fleet's lives


def _two_mode_fleet(seed: int, num_units: int, *, cut: bool):
    """Half the units fail when `a` falls to 0.6, the other half when `b` does; the
    parameter of the other mode stays near new (C-MAPSS FD003: HPC or fan)."""
    rng = np.random.default_rng(seed)
    unit, time, theta, truth, mode = [], [], [], [], []
    for u in range(num_units):
        life = int(rng.integers(80, 140))
        stop = int(rng.uniform(0.4, 0.9) * life) if cut else life
        t = np.arange(1.0, stop + 1.0)
        worn = 1.0 - 0.4 * np.expm1(t / 40.0) / np.expm1(life / 40.0)  # 0.6 at life
        new = 1.0 - 0.01 * t / life
        pair = (worn, new) if u % 2 == 0 else (new, worn)
        noisy = np.stack(pair, 1) + 0.005 * rng.standard_normal((t.size, 2))
        unit += [u + 1] * t.size
        time.append(t)
        theta.append(noisy)
        truth.append(life - stop)
        mode.append("ab"[u % 2])
    rows = (unit, np.concatenate(time), np.concatenate(theta))
    return from_arrays(*rows, ("a", "b")), np.array(truth, float), mode


def test_two_fault_modes_each_learn_their_boundary_from_their_carriers():
    train, _, _ = _two_mode_fleet(0, 20, cut=False)
    test, truth, mode = _two_mode_fleet(1, 12, cut=True)
    result = prognose_trajectories(train, test, None, FAST)
    model = result.model
    np.testing.assert_array_equal(model.carriers.sum(0), [10, 10])
    np.testing.assert_array_equal(model.decides, [True, True])
    np.testing.assert_allclose(model.boundary, [0.6, 0.6], atol=0.02)
    assert list(result.prediction.driver) == mode  # each unit's own mode drives it
    err = result.prediction.rul - truth
    assert np.sqrt(np.mean(err**2)) < 0.4 * truth.std()
    assert any(
        "learned from the units that degraded in them" in n for n in result.notes
    )
    # with one mode's parameter left out, its units are said to fail unseen
    only_a = prognose_trajectories(train.select(["a"]), test.select(["a"]), None, FAST)
    assert any("10 of 20 training units end far" in n for n in only_a.notes)


def test_two_fault_modes_give_a_mixture_prior_sharper_than_one_gaussian(monkeypatch):
    """Each mode's units give its own Gaussian: a unit is not lent half of the other
    mode's drift, so its RUL is nearer the truth and its interval narrower."""
    train, _, _ = _two_mode_fleet(0, 20, cut=False)
    test, truth, mode = _two_mode_fleet(1, 12, cut=True)
    mixed = prognose_trajectories(train, test, None, FAST)
    np.testing.assert_array_equal(mixed.model.modes, [[False, True], [True, False]])
    np.testing.assert_allclose(mixed.model.mode_weight, [0.5, 0.5])
    assert [m["carries"] for m in mixed.model.to_json()["modes"]] == [["b"], ["a"]]
    assert any("mixture of 2 fault modes" in n for n in mixed.notes)
    kept = degradation._modes  # one mode of every unit: the single Gaussian
    monkeypatch.setattr(degradation, "_modes", lambda c, need: kept(c, len(c) + 1))
    single = prognose_trajectories(train, test, None, FAST)
    assert single.model.prior_mean.shape[0] == 1
    rmse, width = {}, {}
    for name, res in (("mixed", mixed), ("single", single)):
        pred = res.prediction
        assert list(pred.driver) == mode
        rmse[name] = np.sqrt(np.mean((pred.rul - truth) ** 2))
        width[name] = np.mean(pred.rul_high - pred.rul_low)
    assert rmse["mixed"] < 0.5 * rmse["single"]
    assert width["mixed"] < 0.7 * width["single"]


def test_errors_name_the_problem(toy):
    train, test, _, _ = toy
    two = train.units(np.arange(15) < 2)
    with pytest.raises(ValueError, match="train: 2 run-to-failure unit"):
        degradation.fit(two)
    with pytest.raises(ValueError, match="run-to-failure unit.*at least 5"):
        prognose_trajectories(two, test, None, FAST)  # FAST: a cubic trend
    with pytest.raises(ValueError, match=r"boundary names \['wear'\]"):
        prognose_trajectories(train, test, {"wear": 1.0}, FAST)
    with pytest.raises(ValueError, match="no parameter's end of life is consistent"):
        prognose_trajectories(train.select(["noise"]), test.select(["noise"]))
    with pytest.raises(ValueError, match="expected the same parameters"):
        prognose_trajectories(train, test.select(["health"]), None, FAST)
    for coverage in (0.0, 1.0, 1.5):
        bad = dataclasses.replace(FAST, coverage=coverage)
        with pytest.raises(ValueError, match=r"coverage must be in \(0, 1\)"):
            prognose_trajectories(train, test, None, bad)
    unit, time, theta = np.repeat([1, 2], [5, 2]), np.arange(7.0), np.ones((7, 2))
    with pytest.raises(ValueError, match="unit 2 has 2 usable row"):
        from_arrays(unit, time, theta, NAMES, label="train")
    time[3] = np.nan
    with pytest.raises(ValueError, match=r"time is not finite in rows \[3\]"):
        from_arrays(unit, time, theta, NAMES, label="train")


def test_three_training_units_are_enough_for_a_given_linear_trend(toy):
    train, test, _, _ = toy
    few = dataclasses.replace(FAST, trend="poly1")
    result = prognose_trajectories(train.units(np.arange(15) < 3), test, None, few)
    assert np.all(np.isfinite(result.prediction.rul))


def test_four_training_units_are_enough_for_the_held_out_check(toy):
    """Leave-one-out keeps 3 units a fold; only a linear trend has a prior there."""
    train, test, _, _ = toy
    free = dataclasses.replace(FAST, trend=None, noise_scale=None)
    result = prognose_trajectories(train.units(np.arange(15) < 4), test, None, free)
    assert result.noise_check["trends"] == ["poly1"]
    assert result.noise_check["cases"] == 4 * 2  # every unit held out, cut twice


@pytest.mark.parametrize(
    "units, trend, match",
    [
        (2, "poly1", "train: 2 run-to-failure unit.*at least 3"),
        (4, "poly3", "train: 4 run-to-failure unit.*at least 5 for a poly3 trend"),
        (3, None, "train: 3 run-to-failure unit.*held-out units needs at least 4"),
    ],
)
def test_too_few_training_units_name_the_fleet_count(toy, units, trend, match):
    train, test, _, _ = toy
    cfg = dataclasses.replace(
        FAST, trend=trend, noise_scale=None if trend is None else 1.0
    )
    with pytest.raises(ValueError, match=match):
        prognose_trajectories(train.units(np.arange(15) < units), test, None, cfg)


def test_write_prognosis_takes_a_real_prognosis(toy, tmp_path):
    from jaxcal.prognosis.report import write_prognosis

    train, test, truth, result = toy
    write_prognosis(tmp_path, result, truth=truth, progress=False)
    assert (tmp_path / "rul.csv").is_file() and (tmp_path / "report.md").is_file()


def test_write_prognosis_draws_the_units_asked_for_and_links_only_those(toy, tmp_path):
    from jaxcal.prognosis.report import unit_label, write_prognosis

    _, _, truth, result = toy
    first = unit_label(result.prediction.unit[0])
    rep = write_prognosis(
        tmp_path, result, truth=truth, progress=False, unit_figures=[first]
    )
    assert sorted(p.name for p in (tmp_path / "units").iterdir()) == [
        f"unit_{first}.png"
    ]
    assert list(rep["figures"]["units"]) == [first]
    page = (tmp_path / "report.md").read_text()
    assert f"[{first}](units/unit_{first}.png)" in page
    second = unit_label(result.prediction.unit[1])
    assert f"units/unit_{second}.png" not in page
    # written again into the same folder with another unit: the first one's figure,
    # not this run's, is gone; a file of the user's is left alone
    (tmp_path / "units" / "notes.txt").write_text("mine")
    write_prognosis(
        tmp_path, result, truth=truth, progress=False, unit_figures=[second]
    )
    assert sorted(p.name for p in (tmp_path / "units").iterdir()) == [
        "notes.txt",
        f"unit_{second}.png",
    ]


def test_phm08_and_score_on_hand_computed_cases():
    # d = -13: exp(13/13) - 1; d = 10: exp(10/10) - 1; d = 0: 0
    assert phm08_score(np.array([-13.0])) == pytest.approx(np.e - 1.0)
    assert phm08_score(np.array([10.0])) == pytest.approx(np.e - 1.0)
    assert phm08_score(np.array([-13.0, 10.0, 0.0])) == pytest.approx(2 * (np.e - 1))
    s = score(rul=[10, 30, 50], low=[5, 31, 40], high=[20, 40, 60], truth=[14, 30, 48])
    assert s["units"] == 3
    assert s["rmse"] == pytest.approx(np.sqrt((16 + 0 + 4) / 3))
    assert s["mean_error"] == pytest.approx(-2 / 3)
    assert s["coverage"] == pytest.approx(2 / 3)  # 30 is below its interval [31, 40]
    assert s["mean_width"] == pytest.approx(44 / 3)
    assert s["phm08_score"] == pytest.approx(np.expm1(4 / 13) + np.expm1(2 / 10))
    with pytest.raises(ValueError, match="truth has 2 values for 3 predicted"):
        score([1, 2, 3], [0, 1, 2], [2, 3, 4], [1, 2])


def test_read_truth_reads_one_number_per_line_and_names_bad_lines(tmp_path):
    path = tmp_path / "RUL.txt"
    path.write_text("112\n98 \n\n69\n")
    np.testing.assert_array_equal(read_truth(str(path)), [112.0, 98.0, 69.0])
    np.testing.assert_array_equal(read_truth(str(path), 3), [112.0, 98.0, 69.0])
    with pytest.raises(ValueError, match="3 true RULs for 4 test units"):
        read_truth(str(path), 4)
    path.write_text("112\nabc\n")
    with pytest.raises(ValueError, match=r"RUL.txt, line 2: 'abc' is not a number"):
        read_truth(str(path))
    path.write_text("1\n-4\n")
    with pytest.raises(ValueError, match="line 2: -4.0 is not a RUL"):
        read_truth(str(path))


HX_LIMIT = 0.45  # fouling at which a heat exchanger is taken out for cleaning
HX_NOISE = {"T_hot_out": 0.05, "T_cold_out": 0.05, "dp_hot": 0.05, "duty": 0.5}


def _hx_fleet(model, seed: int, num_units: int, *, cut: bool):
    """An unlabelled heat-exchanger table (unit, time, conditions, outputs) whose
    fouling rises to :data:`HX_LIMIT` at each unit's last row, and the true RULs."""
    rng = np.random.default_rng(seed)
    low, high = (np.asarray(b) for b in model.condition_range)
    evaluate = jax.vmap(lambda w, th: model.evaluate(w, th)[0])
    frames, truth = [], []
    for u in range(num_units):
        life = int(rng.integers(36, 45))
        t = np.arange(1.0, life + 1.0)
        tau = life * rng.uniform(0.4, 2.0)  # accelerating to nearly linear
        fouling = HX_LIMIT * np.expm1(t / tau) / np.expm1(life / tau)
        dp_coeff = 10.0 + rng.uniform(0.02, 0.15) * t  # clogging, its own pace
        theta = np.stack([fouling, dp_coeff, np.full(life, 0.02)], 1)
        w = rng.uniform(low, high, (life, low.size))
        x = np.asarray(evaluate(jnp.asarray(w), jnp.asarray(theta)))
        x = x + rng.normal(size=x.shape) * list(HX_NOISE.values())
        frame = pd.DataFrame(w, columns=model.condition_names)
        frame[list(model.output_names)] = x
        frame.insert(0, "time", t)
        frame.insert(0, "unit", u + 1)
        if cut:
            rows = int(rng.integers(10, life - 5))
            frame = frame.iloc[:rows]
            truth.append(life - t[rows - 1])
        frames.append(frame)
    return pd.concat(frames, ignore_index=True), np.array(truth)


@pytest.mark.filterwarnings("ignore:jaxcal.calibrate:UserWarning")  # its drift notes
def test_prognose_end_to_end_on_the_heat_exchanger():
    from jaxcal.models import load

    model = load("heat_exchanger")
    train, _ = _hx_fleet(model, 10, 6, cut=False)
    test, truth = _hx_fleet(model, 11, 3, cut=True)
    assert not set(model.parameter_names) & set(train.columns)  # unlabelled
    config = PrognosisConfig(samples=300, trend="poly3", noise_scale=2.0)
    result = prognose(
        model, train, test, theta=("fouling", "dp_coeff"), noise=HX_NOISE,
        boundary={"fouling": HX_LIMIT}, config=config, progress=False,
    )  # fmt: skip
    assert set(result.timings) == {"calibrate", "check", "learn", "predict"}
    assert result.train.names == ("fouling", "dp_coeff") and result.train.unit.size == 6
    # both fleets ran in one calibration; the test units keep their own ids
    assert result.test.unit.tolist() == [1, 2, 3]
    assert result.train.unit.tolist() == [1, 2, 3, 4, 5, 6]
    # the UKF's fouling at each training unit's end is near the limit it failed at
    end = result.train.theta[np.arange(6), result.train.mask.sum(1) - 1, 0]
    np.testing.assert_allclose(end, HX_LIMIT, atol=0.06)
    model_fit = result.model
    assert model_fit.declared[0] and model_fit.decides[0]
    assert model_fit.boundary[0] == HX_LIMIT and model_fit.direction[0] == 1.0
    pred = result.prediction
    np.testing.assert_array_equal(pred.unit, [1, 2, 3])
    assert np.all(np.isfinite(pred.rul)) and np.all(pred.censored == 0.0)
    np.testing.assert_allclose(pred.rul, truth, atol=10.0)
    assert "fouling" in pred.driver
