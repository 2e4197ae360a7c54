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
