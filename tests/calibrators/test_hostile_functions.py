"""Hostile input at the front door (issue 42): user functions, options, globals and
bounds.

A user's function that cannot be traced is a clear error naming the model, the line
and the fix (never a raw JAX error); a method option of the wrong type or value is
refused naming the option and its expected form; a function whose global changed
is traced again (never the old program's answer); every estimate lies inside the
declared bounds, rows where it reached a bound are marked and named.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.tank import NOISE, make_frame, tank, tank_model

import jaxcal
from jaxcal.model import ModelContractError

GIVEN = dict(zip(("level", "temp", "outflow"), NOISE, strict=True))


@pytest.fixture(scope="module")
def frame():
    return make_frame(num_units=2, length=24)


def _calibrate(*args, **kwargs):
    with warnings.catch_warnings():  # the console line, tested where it matters
        warnings.simplefilter("ignore", UserWarning)
        return jaxcal.calibrate(*args, progress=False, **kwargs)


# ---------------------------------------------------------------- untraceable fns


def _numpy_inside(w, theta):
    return tank(w, theta) * np.exp(0.0 * theta[0])  # np on a tracer


def _python_if(w, theta):
    if theta[0] > 1.0:  # a Python branch on a tracer
        return tank(w, theta)
    return 2.0 * tank(w, theta)


def _float_of_theta(w, theta):
    return tank(w, theta) * float(theta[1] + 1.0)


def _callback_without_vmap_method(w, theta):
    out = jax.ShapeDtypeStruct((3,), theta.dtype)
    return jax.pure_callback(lambda w, t: np.asarray(tank(w, t)), out, w, theta)


@pytest.mark.parametrize(
    "fn, match",
    [
        (_numpy_inside, r"calls numpy .* use jax.numpy .*np.exp\(0.0 \* theta"),
        (_python_if, r"branches in Python .* jnp.where.*if theta\[0\] > 1.0"),
        (_float_of_theta, r"converts a traced input to a Python number.*float\("),
        (_callback_without_vmap_method, r"pure_callback without vmap_method.*'seq"),
    ],
    ids=["numpy", "python-if", "float", "pure-callback"],
)
@pytest.mark.parametrize("method", ["ukf", "ls"])
def test_a_function_that_cannot_be_traced_names_the_model_line_and_fix(
    frame, fn, match, method
):
    model = tank_model(fn, name="hostile")
    with pytest.raises(ModelContractError, match=match) as err:
        _calibrate(model, frame, method, noise=GIVEN)
    assert str(err.value).startswith("model 'hostile': fn(w, theta) ")
    assert "test_hostile_functions.py:" in str(err.value)  # the user's line


def test_the_same_functions_still_evaluate_on_concrete_numbers():
    # Untraced, numpy and Python branches work: only the traced use is refused.
    w, theta = jnp.array([10.0, 1.0]), jnp.array([1.2, 0.1])
    for fn in (_numpy_inside, _python_if, _float_of_theta):
        x, info = tank_model(fn).evaluate(w, theta)
        assert x.shape == (3,) and bool(info.valid)


def test_a_callback_with_vmap_method_calibrates(frame):
    def callback(w, theta):
        out = jax.ShapeDtypeStruct((3,), theta.dtype)
        host = lambda w, t: np.asarray(tank(w, t), t.dtype)  # noqa: E731
        return jax.pure_callback(host, out, w, theta, vmap_method="sequential")

    model = tank_model(callback, name="callback")
    result = _calibrate(model, frame, "ukf", noise=GIVEN, theta=["leak"])
    assert result.valid.all() and np.isfinite(result.theta).all()


# ---------------------------------------------------------------- options


@pytest.mark.parametrize(
    "method, options, match",
    [
        ("ukf", {"q": np.inf}, r"option q=inf is not a finite number > 0"),
        ("ukf", {"q": "0.01"}, r"option q='0.01' is not a finite number > 0"),
        ("ukf", {"q": -0.1}, r"q=-0.1 is not a finite number > 0"),
        ("ukf", {"prior_std": np.nan}, r"prior_std=nan is not a finite number > 0"),
        ("ukf", {"alpha": True}, r"alpha=True is not a finite number > 0"),
        ("ukf", {"beta": np.inf}, r"beta=inf is not a finite number \("),
        ("ukf", {"jitter": -1e-9}, r"jitter=-1e-09 is not a finite number >= 0"),
        ("ukf", {"return_cov": "yes"}, r"return_cov='yes' is not True or False"),
        ("ls", {"window": 8.5}, r"option window=8.5 is not an integer >= 1"),
        ("ls", {"window": 0}, r"window=0 is not an integer >= 1"),
        ("ls", {"num_iters": "3"}, r"num_iters='3' is not an integer >= 1"),
        ("ls", {"prior_std": 0.0}, r"prior_std=0.0 is not a finite number > 0 or No"),
        ("ls", {"damping_factor": 1.0}, r"damping_factor=1.0 is not a finite number >"),
        ("ukf", {"state_std": "big"}, r"state_std='big' is not a finite number >= 0"),
        ("ukf", {"state_q": [0.1, np.inf]}, r"state_q=\[0.1, inf\] is not"),
        ("e2e", {"e2e_copies": 0}, r"e2e_copies=0 is not an integer >= 1"),
        ("e2e", {"e2e_window": 2.5}, r"e2e_window=2.5 is not an integer >= 1 or No"),
        ("e2e", {"e2e_config": {"epochs": 3}}, r"e2e_config must be an E2EConfig"),
    ],
)  # fmt: skip
def test_an_option_of_the_wrong_type_or_value_names_the_option(
    frame, method, options, match
):
    with pytest.raises(ValueError, match=match) as err:
        _calibrate(tank_model(), frame, method, noise=GIVEN, **options)
    assert f"method={method!r}" in str(err.value)


def test_options_of_the_accepted_forms_calibrate(frame):
    result = _calibrate(
        tank_model(), frame, "ls", noise=GIVEN, window=np.int64(4), num_iters=2,
        prior_std=None, damping_factor=5,
    )  # fmt: skip
    assert result.valid.all()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"theta": []}, r"theta=\[\] names no parameter: give at least one of \['le"),
        ({"theta": "leak"}, r"theta must be a list of parameter names, got the str"),
        ({"theta": [1, 2]}, r"theta must be a list of parameter names \(e.g. theta"),
        ({"theta": 3}, r"theta must be a list of parameter names"),
        ({"outputs": ()}, r"outputs=\[\] names no output"),
        ({"outputs": "level"}, r"write outputs=\['level'\]"),
    ],
    ids=["empty", "string", "numbers", "number", "no-outputs", "output-string"],
)
def test_theta_and_outputs_are_lists_of_names_never_read_as_all(frame, kwargs, match):
    with pytest.raises(ValueError, match=match):
        _calibrate(tank_model(), frame, "ukf", noise=GIVEN, **kwargs)


# ---------------------------------------------------------------- globals

GAIN = {"level": 1.0}  # a global the model reads (a dict: reassigned in place)


def _reads_a_global(w, theta):
    return tank(w, theta) * jnp.array([GAIN["level"], 1.0, 1.0])


def test_a_changed_global_gets_a_new_program_not_the_old_answer(frame):
    from jaxcal.calibrators.programs import compiled

    model = tank_model(_reads_a_global, name="reads_a_global")
    try:
        first = _calibrate(model, frame, "ls", noise=GIVEN, window=4)
        builds = dict(compiled._COUNTS)
        again = _calibrate(model, frame, "ls", noise=GIVEN, window=4)
        assert dict(compiled._COUNTS) == builds  # unchanged: the program is reused
        GAIN["level"] = 0.8  # the level reads lower: the leak 0.8 times its value
        changed = _calibrate(model, frame, "ls", noise=GIVEN, window=4)
        fresh = _calibrate(
            tank_model(_reads_a_global, name="fresh"), frame, "ls", noise=GIVEN,
            window=4,
        )  # fmt: skip
    finally:
        GAIN["level"] = 1.0
    np.testing.assert_array_equal(again.theta, first.theta)
    np.testing.assert_allclose(changed.theta, fresh.theta, rtol=1e-5)
    leak = first.theta[:, 0]
    assert np.median(changed.theta[:, 0] / leak) == pytest.approx(0.8, rel=0.05)


# ---------------------------------------------------------------- bounds


def _infinite_at_bound(w, theta):
    """The tank whose level is infinite at the leak's lower bound (0.5)."""
    heat, inflow = w[0], w[1]
    leak, loss = theta[0], theta[1]
    level = inflow / (leak - 0.5)
    temp = 20.0 + heat / (inflow * (1.0 + loss))
    return jnp.stack([level, temp, leak * inflow * (1.0 - 0.1 * loss)])


def _frame_of(fn, frame, leak, seed=3):
    """``frame``'s conditions with outputs of ``fn`` at ``leak`` (loss 0.2)."""
    rng = np.random.default_rng(seed)
    theta = np.tile([leak, 0.2], (len(frame), 1))
    x = np.asarray(jax.vmap(fn)(frame[["heat", "inflow"]].to_numpy(), theta))
    out = frame.copy()
    out[list(GIVEN)] = x + NOISE * rng.standard_normal(x.shape)
    return out


def _last(result):
    """The last row's theta of each unit."""
    order = np.lexsort((result.time, result.unit))
    ends = np.flatnonzero(np.diff(result.unit[order], append=-1) != 0)
    return result.theta[order][ends]


def _inside(result):
    low, high = result.problem.theta_low, result.problem.theta_high
    return bool(np.all((result.theta >= low) & (result.theta <= high)))


def test_an_output_infinite_at_a_bound_keeps_the_ukf_inside_and_converging(frame):
    data = _frame_of(_infinite_at_bound, frame, leak=0.55)
    model = tank_model(_infinite_at_bound, name="infinite_at_bound")
    result = _calibrate(model, data, "ukf", noise=GIVEN, outlier_z=None)
    assert _inside(result) and np.isfinite(result.theta).all()
    np.testing.assert_allclose(_last(result)[:, 0], 0.55, atol=0.01)


@pytest.mark.parametrize("method", ["ukf", "ls"])
def test_data_beyond_the_box_keep_theta_inside_and_mark_the_rows(frame, method):
    data = _frame_of(tank, frame, leak=2.6)  # the box is [0.5, 2]
    with pytest.warns(UserWarning, match=r"leak at its upper bound 2 on \d+ rows"):
        result = jaxcal.calibrate(
            tank_model(), data, method, noise=GIVEN, outlier_z=None, progress=False
        )
    assert _inside(result)
    at = result.at_bound
    np.testing.assert_array_equal(at, result.theta[:, 0] >= 2.0 - 1e-5 * 1.5)
    assert at[result.valid].mean() > 0.5  # most rows: the data want leak 2.6
    note = next(n for n in result.notes if "reached a bound" in n)
    assert f"on {int((at & result.valid).sum())} of {len(at)} rows" in note
    assert result.to_frame()["at_bound"].tolist() == at.tolist()


def test_a_result_inside_its_box_marks_no_row(frame):
    result = _calibrate(tank_model(), frame, "ls", noise=GIVEN, window=4)
    assert _inside(result) and not result.at_bound.any()
    assert not any("reached a bound" in n for n in result.notes)


def test_any_method_s_theta_is_clipped_into_the_box_and_marked():
    from jaxcal.calibrators.front.rows import inside_box

    class Box:  # the problem's box, all inside_box reads
        theta_low, theta_high = np.array([0.5, 0.0]), np.array([2.0, 0.5])

    theta = np.array([[1.0, 0.1], [2.7, 0.1], [1.0, -0.3], [np.nan, 0.2], [2.0, 0.5]])
    before = np.array([False, False, False, False, True])  # the prior's row
    clipped, at = inside_box(theta, Box, before)
    np.testing.assert_array_equal(
        clipped, [[1.0, 0.1], [2.0, 0.1], [1.0, 0.0], [np.nan, 0.2], [2.0, 0.5]]
    )
    np.testing.assert_array_equal(at, [False, True, True, False, False])


def test_at_bound_is_saved_and_loaded(frame, tmp_path):
    data = _frame_of(tank, frame, leak=2.6)
    result = _calibrate(tank_model(), data, "ls", noise=GIVEN, window=4)
    loaded = jaxcal.CalibrationResult.load(result.save(tmp_path / "r.parquet"))
    np.testing.assert_array_equal(loaded.at_bound, result.at_bound)
    assert loaded.at_bound.any()
