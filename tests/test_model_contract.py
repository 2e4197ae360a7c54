"""A model's contract: what its functions return (shapes, dtypes, the step's pair),
the names it declares (no clash, no reserved column name) and the parameter specs it
accepts. Every breach is a clear error naming the model's declared names and what
came back, never a silent wrong answer or a raw JAX error (issue 25)."""

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.model import ModelContractError

W, THETA = jnp.array([1.5, 2.0]), jnp.array([1.2])
PARAMS = {"p": (1.0, 0.5, 2.0)}
OUTPUTS = ("y1", "y2", "y3")


def _three(w, theta):
    return jnp.stack([w[0] * theta[0], w[1] + theta[0], w[0] * w[1] * theta[0]])


def _static(fn, outputs=OUTPUTS, **kw):
    return jaxcal.Model.from_function(
        fn, conditions=("a", "b"), parameters=PARAMS, outputs=outputs, **kw
    )


def _stateful(step, init_state=np.zeros(1), states=("s",)):
    return jaxcal.Model.from_step(
        step, init_state=init_state, states=states, conditions=("a", "b"),
        parameters=PARAMS, outputs=("y1",),
    )  # fmt: skip


@pytest.mark.parametrize(
    "fn, match",
    [
        (lambda w, t: _three(w, t)[:2], r"2 values for the 3 declared outputs"),
        (
            lambda w, t: jnp.concatenate([_three(w, t), w[:1]]),
            r"4 values for the 3 declared outputs.*not dropped",
        ),
        (lambda w, t: w[0] * t[0], r"a scalar \(shape \(\)\)"),
        (lambda w, t: [w[0] * t[0], w[1], w[0]], r"Python list of 3 items"),
        (lambda w, t: _three(w, t)[:, None], r"shape \(3, 1\).*reshape"),
        (lambda w, t: _three(w, t).astype(jnp.int32), r"int32 values.*no gradient"),
        (lambda w, t: _three(w, t) > 0, r"bool values"),
        (lambda w, t: _three(w, t).astype(jnp.complex64), r"complex64 values"),
        (lambda w, t: (w[0], w[1], t[0]), r"tuple of 3 items.*\(x, valid\)"),
        (lambda w, t: (_three(w, t), jnp.ones(3, bool)), r"validity flag of shape"),
    ],
    ids=[
        "2-of-3", "4-of-3", "scalar", "list", "3x1", "int", "bool", "complex",
        "tuple", "valid-per-output",
    ],
)  # fmt: skip
def test_an_output_that_breaks_the_declaration_is_a_clear_error(fn, match):
    model = _static(fn)
    with pytest.raises(ModelContractError, match=match) as err:
        jax.jit(model.evaluate)(W, THETA)  # checked when JAX traces the model
    assert "['y1', 'y2', 'y3']" in str(err.value) or "flag" in str(err.value)
    assert "model 'model': fn(w, theta)" in str(err.value)
    with pytest.raises(ModelContractError, match=match):
        model.evaluate(W, THETA)  # and outside jit


def test_a_scalar_is_refused_even_for_one_declared_output():
    # One form for every model (x is [S]); the error says how to return it.
    model = _static(lambda w, t: w[0] * t[0], outputs=("y",))
    with pytest.raises(ModelContractError, match=r"scalar.*\[1\] float array"):
        jax.eval_shape(model.evaluate, W, THETA)


def test_two_of_three_outputs_no_longer_calibrates_to_a_silent_answer():
    rng = np.random.default_rng(0)
    w = rng.uniform(1.0, 2.0, (6, 2))
    x = np.asarray(jax.vmap(_three, (0, None))(jnp.asarray(w), THETA))
    frame = pd.DataFrame({"a": w[:, 0], "b": w[:, 1], "y1": x[:, 0], "y2": x[:, 1]})
    frame["y3"] = x[:, 2]
    model = _static(lambda w, t: _three(w, t)[:2])
    with pytest.raises(ModelContractError, match="2 values for the 3 declared"):
        jaxcal.calibrate(model, frame, "ls", noise=dict.fromkeys(OUTPUTS, 0.01))


def test_hinted_and_effect_functions_are_held_to_the_same_contract():
    hinted = _static(
        _three,
        hinted_fn=lambda w, t, h: (_three(w, t)[:2], None, h),
        initial_hint=lambda: jnp.zeros(()),
    )
    with pytest.raises(ModelContractError, match=r"hinted_fn.*2 values for the 3"):
        jax.eval_shape(hinted.evaluate_hinted, W, THETA, jnp.zeros(()))
    effects = _static(
        _three,
        effects={"bias": (0.0, -1.0, 1.0)},
        effect_fn=lambda w, t, e: [w[0], w[1], e[0]],
    )
    with pytest.raises(ModelContractError, match=r"effect_fn.*Python list"):
        effects.evaluate_effects(W, THETA, jnp.zeros(1))


def test_a_step_function_returning_only_x_is_a_clear_error():
    model = _stateful(lambda s, w, t: jnp.stack([s[0] + w[0] * t[0]]))
    state = model.init_state(W, THETA)
    with pytest.raises(ModelContractError, match=r"single array of shape \(1,\)"):
        jax.jit(model.step)(state, W, THETA)


@pytest.mark.parametrize(
    "step, match",
    [
        (
            lambda s, w, t: (jnp.concatenate([s, s]), s + w[0]),
            r"step\(state, w, theta\) returned 2 values for the 1 declared states",
        ),
        (lambda s, w, t: (s[0], s + w[0]), r"a scalar.*declared state \['s'\]"),
        (lambda s, w, t: (s.astype(jnp.int32), s + w[0]), r"int32 values"),
    ],
    ids=["two-states", "scalar-state", "int-state"],
)
def test_a_state_of_the_wrong_shape_or_dtype_names_the_declared_states(step, match):
    model = _stateful(step)
    with pytest.raises(ModelContractError, match=match):
        jax.eval_shape(model.step, jnp.zeros(1), W, THETA)


def test_an_initial_state_of_the_wrong_size_is_refused():
    step = lambda s, w, t: (s, s + w[0])  # noqa: E731
    with pytest.raises(ModelContractError, match=r"init_state has shape \(2,\)"):
        _stateful(step, init_state=np.zeros(2))  # at construction: a fixed array
    model = _stateful(step, init_state=lambda w0, t: jnp.zeros(3))
    with pytest.raises(ModelContractError, match=r"init_state\(w0, theta\) returned 3"):
        model.init_state(W, THETA)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"outputs": ("y1", "y2", "time")}, r"output 'time': the name is reserved"),
        ({"outputs": ("y1", "unit", "y3")}, r"output 'unit': the name is reserved"),
        ({"conditions": ("a", "split")}, r"condition 'split'.*reserved"),
        ({"parameters": {"valid": (1.0, 0.5, 2.0)}}, r"parameter 'valid'.*reserved"),
        ({"parameters": {"a": (1.0, 0.5, 2.0)}}, r"'a' is both a condition and a "),
        ({"outputs": ("y1", "b", "y3")}, r"'b' is both a condition and an output"),
        (
            {"effects": {"p": (0.0, -1.0, 1.0)}, "effect_fn": lambda w, t, e: w},
            r"'p' is both a parameter and an effect",
        ),
    ],
    ids=[
        "output-time", "output-unit", "condition-split", "parameter-valid",
        "parameter-like-condition", "output-like-condition", "effect-like-parameter",
    ],
)  # fmt: skip
def test_name_clashes_and_reserved_names_are_refused_at_construction(kwargs, match):
    spec = dict(conditions=("a", "b"), parameters=PARAMS, outputs=OUTPUTS)
    spec.update(kwargs)
    with pytest.raises(ValueError, match=match):
        jaxcal.Model.from_function(_three, **spec)


def test_a_state_named_like_a_condition_is_refused_like_an_output_is_not():
    with pytest.raises(ValueError, match=r"'a' is both a condition and a state"):
        _stateful(lambda s, w, t: (s, s), states=("a",))
    # an output that is the state it measures keeps the state's name (issue 42)
    assert _stateful(lambda s, w, t: (s, s), states=("y1",)).state_names == ("y1",)


@pytest.mark.parametrize(
    "parameters, match",
    [
        ({"leak": 1.0}, r"parameters\['leak'\]: got 1.0; expected \(nominal, low"),
        ({"leak": "abc"}, r"parameters\['leak'\]: got 'abc'"),
        (["leak"], r"parameters\[0\]: got 'leak'; expected \(name, nominal"),
        ("leak", r"parameters: got 'leak'"),
        ({"leak": (1.0, "low", 2.0)}, r"must be numbers"),
    ],
    ids=["bare-nominal", "string", "list-of-names", "one-string", "non-number"],
)
def test_a_parameter_spec_of_another_form_lists_the_accepted_forms(parameters, match):
    with pytest.raises(ValueError, match=match) as err:
        jaxcal.Model.from_function(
            _three, conditions=("a", "b"), parameters=parameters, outputs=OUTPUTS
        )
    if "numbers" not in match:
        assert "{name: (nominal, low, high)}" in str(err.value)


def test_accepted_parameter_forms_build_the_same_parameters():
    rows = [("p", 1.0, 0.5, 2.0), jaxcal.Parameter("q", 0.0, -1.0, 1.0, "m")]
    model = jaxcal.Model.from_function(
        lambda w, t: _three(w, t[:1]), conditions=("a", "b"), parameters=rows,
        outputs=OUTPUTS,
    )  # fmt: skip
    assert model.parameters == (
        jaxcal.Parameter("p", 1.0, 0.5, 2.0, "-"),
        jaxcal.Parameter("q", 0.0, -1.0, 1.0, "m"),
    )
    x, info = jax.jit(model.evaluate)(W, jnp.array([1.2, 0.0]))
    np.testing.assert_allclose(x, _three(W, THETA))
    assert bool(info.valid)


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: _static("tank"), r"fn must be a function fn\(w, theta\), got a str"),
        (lambda: _static(None), r"fn must be a function fn\(w, theta\), got a None"),
        (lambda: _static(lambda theta: theta), r"fn is <lambda>\(theta\).*fn\(w, t"),
        (lambda: _static(lambda s, w, t: t), r"missing a required argument: 't'"),
        (
            lambda: _stateful(lambda w, t: (w, t)),
            r"step is <lambda>\(w, t\), which cannot be called as step\(state, w, t",
        ),
        (
            lambda: _stateful(lambda s, w, t: (s, s), init_state=lambda w0: w0),
            r"init_state is <lambda>\(w0\).*init_state\(w0, theta\)",
        ),
        (lambda: _static(_three, input_check="w > 0"), r"input_check must be a fun"),
        (
            lambda: _static(
                _three, effects={"e": (0.0, -1.0, 1.0)}, effect_fn=lambda w, t: w
            ),
            r"effect_fn is <lambda>\(w, t\).*effect_fn\(w, theta, e\)",
        ),
    ],
    ids=[
        "string", "none", "one-argument", "three-arguments", "step-two-arguments",
        "init-one-argument", "check-string", "effect-two-arguments",
    ],
)  # fmt: skip
def test_a_function_that_cannot_be_called_so_is_refused_at_construction(build, match):
    with pytest.raises(ModelContractError, match=match) as err:
        build()
    assert "model 'model'" in str(err.value)


def test_defaults_keywords_and_partials_are_accepted_signatures():
    import functools

    def scaled(w, theta, gain=1.0, *, offset=0.0):
        return gain * _three(w, theta) + offset

    for fn in (scaled, functools.partial(scaled, gain=2.0), jax.jit(_three)):
        x, _ = _static(fn).evaluate(W, THETA)
        assert x.shape == (3,)
