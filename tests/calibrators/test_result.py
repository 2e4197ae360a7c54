"""CalibrationResult kept and shown: Parquet save/load round trip, plot, summary."""

import dataclasses

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure
from support.tank import MODEL, NOISE, make_frame

import jaxcal
from jaxcal.calibrators.front.result import CalibrationResult

ARRAYS = ("theta", "theta_std", "states", "xhat", "valid", "reason", "partial")
NAMES = ("theta_names", "output_names", "state_names", "notes", "method")


@pytest.fixture(scope="module")
def frame():
    frame = make_frame(num_units=2, length=60)
    frame.loc[frame.index[:2], "heat"] = 500.0  # outside the model's box: skipped
    return frame


@pytest.fixture(scope="module", params=["ukf", "ls"])
def result(request, frame):
    noise = dict(zip(MODEL.output_names, NOISE, strict=True))
    with pytest.warns(UserWarning, match="2 of 120 rows flagged"):
        return jaxcal.calibrate(MODEL, frame, method=request.param, noise=noise)


def _assert_same(loaded, result):
    for name in (*ARRAYS, "unit", "time"):
        a, b = getattr(result, name), getattr(loaded, name)
        if a is None:
            assert b is None, name
            continue
        assert b.dtype == a.dtype and b.shape == a.shape, name
        np.testing.assert_array_equal(b, a, err_msg=name)  # NaN == NaN here
    for name in NAMES:
        assert getattr(loaded, name) == getattr(result, name), name
    assert loaded.noise_source == result.noise_source == "given"


def test_save_load_round_trips_every_field(result, tmp_path):
    assert (~result.valid).sum() == 2 and result.theta_std is not None
    path = result.save(tmp_path / "sub" / "result.parquet")
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]  # no temp
    loaded = CalibrationResult.load(path)
    _assert_same(loaded, result)
    assert loaded.problem is None
    assert loaded.variable_units() == result.variable_units()
    assert loaded.variable_units()["leak"] == "1/s"
    # an open format: any Parquet reader sees to_frame()'s columns
    pd.testing.assert_frame_equal(pd.read_parquet(path), result.to_frame())
    # saved again without its model, nothing is lost
    again = CalibrationResult.load(
        loaded.save(tmp_path / "again.parquet"), model="support.tank:MODEL"
    )
    _assert_same(again, result)
    assert again.problem.to_json() == result.problem.to_json()


def test_load_with_the_model_restores_the_problem(result, tmp_path):
    path = result.save(tmp_path / "result.parquet")
    loaded = CalibrationResult.load(path, model=MODEL)
    assert loaded.problem.model is MODEL
    assert loaded.problem.to_json() == result.problem.to_json()
    other = jaxcal.Model.from_function(
        lambda w, theta: w, conditions=("a", "b"), parameters={"k": (1.0, 0.0, 2.0)},
        outputs=("level", "temp"), name="other",
    )  # fmt: skip
    with pytest.raises(ValueError, match="result.parquet.*'other' is not the result"):
        CalibrationResult.load(path, model=other)


def test_a_result_without_a_problem_says_so():
    bare = CalibrationResult(
        theta=np.zeros((1, 1)), theta_std=None, states=None, state_names=(),
        xhat=np.zeros((1, 1)), valid=np.ones(1, bool), reason=np.array(["ok"]),
        theta_names=("a",), output_names=("y",), unit=np.zeros(1, np.int64),
        time=np.zeros(1), method="ukf", problem=None,
    )  # fmt: skip
    with pytest.raises(ValueError, match="no problem.*model="):
        bare.noise_source  # noqa: B018
    assert "a = 0" in bare.summary()


@pytest.mark.parametrize(
    "content",
    [b"not parquet at all", "foreign"],
    ids=["corrupt", "foreign"],
)
def test_load_rejects_other_files_naming_them(tmp_path, content):
    path = tmp_path / "other.parquet"
    if content == "foreign":
        pd.DataFrame({"a": [1.0, 2.0]}).to_parquet(path)
    else:
        path.write_bytes(content)
    with pytest.raises(ValueError, match=f"{path}: not a"):
        CalibrationResult.load(path)
    with pytest.raises(ValueError, match="missing.parquet: no such file"):
        CalibrationResult.load(tmp_path / "missing.parquet")


def test_plot_draws_one_panel_per_parameter_with_band_and_skipped_rows(result):
    fig = result.plot()
    assert isinstance(fig, Figure)
    axes = fig.get_axes()
    assert len(axes) == len(result.theta_names) == 2
    assert axes[0].get_ylabel() == "leak [1/s]" and axes[1].get_ylabel() == "loss"
    assert len(axes[0].collections) == 2  # a ±2 std band per unit
    markers = [line.get_marker() for line in axes[0].get_lines()]
    assert "x" in markers  # the skipped rows
    assert len(result.plot(units=[1]).get_axes()[0].collections) == 1
    with pytest.raises(ValueError, match=r"unit\(s\) \[7\]"):
        result.plot(units=[7])


def test_e2e_like_result_without_std_round_trips_and_plots_no_band(result, tmp_path):
    e2e = dataclasses.replace(result, theta_std=None, partial=None, method="e2e")
    loaded = CalibrationResult.load(e2e.save(tmp_path / "e2e.parquet"))
    _assert_same(loaded, e2e)
    fig = loaded.plot(max_units=1)
    assert all(not ax.collections for ax in fig.get_axes())
    assert [t.get_text() for t in fig.get_axes()[0].get_legend().get_texts()] == [
        "unit 0",
        "skipped",
    ]
    assert "±" not in loaded.summary() and "leak = " in loaded.summary()


def test_hidden_states_round_trip(result, tmp_path):
    states = np.random.default_rng(0).normal(size=(len(result.valid), 2))
    states[:3] = np.nan  # before a unit's first used row
    with_states = dataclasses.replace(result, states=states, state_names=("z1", "z2"))
    loaded = CalibrationResult.load(with_states.save(tmp_path / "states.parquet"))
    _assert_same(loaded, with_states)
    assert "; state z1 = " in loaded.summary()


def test_summary_gives_each_units_last_estimate_with_std(result):
    lines = result.summary().splitlines()
    assert lines[0].startswith(f"{result.method}: 120 rows in 2 unit(s), 2 skipped")
    last = np.flatnonzero((result.unit == 1) & (result.time == 59))[0]
    leak, std = result.theta[last, 0], result.theta_std[last, 0]
    assert lines[2] == (
        f"unit 1 at time 59: leak = {leak:.4g} ± {std:.2g} 1/s, "
        f"loss = {result.theta[last, 1]:.4g} ± {result.theta_std[last, 1]:.2g}"
    )
    assert str(result) == result.summary()
    assert result.summary(max_units=1).splitlines()[-1] == "... and 1 more unit(s)"
