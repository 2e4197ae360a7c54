"""The Model protocol, the Dataset container, its readers and the Problem."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.data.readers import read_dataset
from jaxcal.problem import Problem


def _fn(w, theta):
    return jnp.stack([w[0] * theta[0], w[1] + theta[0] * theta[1]])


def _model():
    return jaxcal.Model.from_function(
        _fn,
        conditions=("a", "b"),
        parameters={"p": (1.0, 0.5, 2.0), "q": (0.0, -1.0, 1.0, "m")},
        outputs=("y1", "y2"),
        condition_range=([0.0, -10.0], [5.0, 10.0]),
    )


def test_from_function_names_units_bounds_and_evaluate():
    model = _model()
    assert model.condition_names == ("a", "b")
    assert model.parameter_names == ("p", "q")
    assert model.unit_of("q") == "m"
    np.testing.assert_array_equal(model.nominal, [1.0, 0.0])
    x, info = jax.jit(model.evaluate)(jnp.array([2.0, 1.0]), jnp.array([1.5, 0.5]))
    np.testing.assert_allclose(x, [3.0, 1.75])
    assert bool(info.valid)
    _, info = model.evaluate(jnp.array([9.0, 1.0]), jnp.array([1.5, 0.5]))
    assert not bool(info.valid)  # outside condition_range
    _, info = model.evaluate(jnp.array([1.0, jnp.nan]), jnp.array([1.5, 0.5]))
    assert not bool(info.valid)


def test_restrict_holds_undeclared_parameters_and_selects_outputs():
    model = _model()
    measure = model.restrict(["q"], ["y2"], theta_base=np.array([2.0, 0.0]))
    np.testing.assert_allclose(measure(jnp.array([1.0, 1.0]), jnp.array([0.25])), [1.5])


def test_restrict_places_declared_parameters_in_any_order_with_their_sweeps():
    def fn(w, theta):  # every parameter's place visible in the outputs
        return jnp.stack([theta[0] + 10 * theta[1] + 100 * theta[2], w[0] * theta[1]])

    model = jaxcal.Model.from_function(
        fn,
        conditions=("a",),
        parameters={"p": (1.0, 0.0, 2.0), "q": (0.5, 0.0, 1.0), "r": (0.25, 0.0, 1.0)},
        outputs=("y", "z"),
    )
    measure = model.restrict(["r", "p"])  # declared out of order, q held
    w, theta = jnp.array([3.0]), jnp.array([0.75, 1.5])
    full = jnp.array([1.5, 0.5, 0.75])  # p, q, r
    np.testing.assert_array_equal(measure(w, theta), model.evaluate(w, full)[0])
    # one tangent sweep per declared parameter: d/dr = 100, d/dp = 1 on y
    jac = jax.jit(jax.jacfwd(measure, argnums=1))(w, theta)
    np.testing.assert_array_equal(jac, [[100.0, 1.0], [0.0, 0.0]])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"parameters": {"p": (3.0, 0.5, 2.0)}}, "outside"),
        ({"parameters": {"p": (1.0, 2.0, 0.5)}}, "low < high"),
        ({"outputs": ("y", "y")}, "repeated"),
        ({"conditions": "ab"}, "sequence of names"),
        ({"warm_fn": lambda w, th, e, z0: (w, True, z0)}, "warm_size"),
        ({"warm_size": 3}, "warm_fn"),
    ],
)
def test_bad_model_declarations_are_clear_errors(kwargs, match):
    spec = dict(
        conditions=("a", "b"), parameters={"p": (1.0, 0.5, 2.0)}, outputs=("y",)
    )
    spec.update(kwargs)
    with pytest.raises(ValueError, match=match):
        jaxcal.Model.from_function(_fn, **spec)


def test_a_warm_started_form_returns_its_solution_and_checks_its_output():
    def warm(w, theta, e, z0):  # a solver's start z0 and its solution z
        del e
        return _fn(w, theta), True, jnp.where(jnp.isfinite(z0), z0, 0.0) + 1.0

    model = jaxcal.Model.from_function(
        _fn, conditions=("a", "b"), parameters={"p": (1.0, 0.5, 2.0),
        "q": (0.0, -1.0, 1.0)}, outputs=("y1", "y2"), warm_fn=warm, warm_size=1,
        condition_range=([0.0, -10.0], [5.0, 10.0]),
    )  # fmt: skip
    w, theta = jnp.array([1.0, 2.0]), jnp.array([1.5, 0.5])
    x, info, z = model.evaluate_from(w, theta, jnp.zeros(0), jnp.array([jnp.nan]))
    np.testing.assert_array_equal(x, model.evaluate(w, theta)[0])
    assert bool(info.valid) and float(z[0]) == 1.0
    assert not bool(model.evaluate_from(jnp.array([9.0, 2.0]), theta, jnp.zeros(0),
                                        z)[1].valid)  # fmt: skip  # outside the box
    with pytest.raises(ValueError, match="no warm_fn"):
        _model().evaluate_from(w, theta, jnp.zeros(0), z)


def test_stateful_model_steps_and_static_evaluate_refuses_it():
    def step(state, w, theta):
        new = state * theta[0] + w[0]
        return new, jnp.stack([new[0] + w[1]])

    model = jaxcal.Model.from_step(
        step, init_state=np.zeros(1), states=("s",), conditions=("u", "v"),
        parameters={"a": (0.5, 0.0, 1.0)}, outputs=("y",),
    )  # fmt: skip
    assert model.is_stateful
    state = model.init_state(jnp.zeros(2), jnp.array([0.5]))
    state, x, info = model.step(state, jnp.array([1.0, 2.0]), jnp.array([0.5]))
    np.testing.assert_allclose(x, [3.0])
    assert bool(info.valid)
    with pytest.raises(ValueError, match="hidden states"):
        model.evaluate(jnp.zeros(2), jnp.array([0.5]))


def _frame(n=12):
    rng = np.random.default_rng(0)
    frame = pd.DataFrame({"a": rng.uniform(1, 2, n), "b": rng.uniform(0, 1, n)})
    frame["y1"], frame["y2"] = frame.a * 1.2, frame.b + 0.1
    frame["unit"] = np.repeat([7, 3], n // 2)
    frame["time"] = np.tile(np.arange(n // 2)[::-1], 2)
    return frame


def test_csv_and_parquet_read_into_the_same_dataset(tmp_path):
    frame = _frame()
    frame.to_csv(tmp_path / "d.csv", index=False)
    frame.to_parquet(tmp_path / "d.parquet")
    a = read_dataset(tmp_path / "d.csv", _model())
    b = read_dataset(tmp_path / "d.parquet", _model())
    np.testing.assert_allclose(a.x, b.x)
    assert a.units.tolist() == [7, 3]
    padded = a.padded()
    assert padded.w.shape == (2, 6, 2) and padded.mask.all()
    # rows come back in the file's order
    back = padded.to_rows(padded.x, a.num_rows)
    np.testing.assert_allclose(back, a.x)
    # within a unit the streams run in time order
    assert np.all(np.diff(a.time[padded.rows[0]]) > 0)


def test_a_model_carries_its_own_file_formats(tmp_path):
    path = tmp_path / "d.own"
    path.write_text("rows")
    seen = {}

    def reader(p, *, nonfinite, rename, **options):
        seen.update(path=p, nonfinite=nonfinite, rename=rename, **options)
        return read_dataset(_frame(), _model())

    model = dataclasses.replace(_model(), file_readers={".own": reader})
    data = read_dataset(path, model, nonfinite="drop", stride=2)
    assert data.num_rows == 12
    assert seen == {"path": str(path), "nonfinite": "drop", "rename": None, "stride": 2}
    with pytest.raises(ValueError, match=r"type '.own'; .*read with the model"):
        read_dataset(path)
    with pytest.raises(ValueError, match=r"type '.own'; expected .csv, .parquet$"):
        read_dataset(path, _model())


def test_unknown_and_missing_columns_list_expected_and_found(tmp_path):
    frame = _frame().rename(columns={"y1": "Y_one"})
    with pytest.raises(ValueError, match=r"unknown columns \['Y_one'\].*found"):
        read_dataset(frame, _model())
    data = read_dataset(frame, _model(), rename={"Y_one": "y1"})
    assert data.output_names == ("y1", "y2")
    with pytest.raises(ValueError, match="missing conditions"):
        read_dataset(_frame().drop(columns="a"), _model())


def test_nonfinite_rows_named_or_dropped(tmp_path):
    frame = _frame()
    frame.loc[[3, 5], "y2"] = np.nan
    frame.to_csv(tmp_path / "d.csv", index=False)
    # partial rows (y1 still there) are kept by default; partial=False: as any NaN
    with pytest.raises(ValueError, match=r"d.csv.*column y2: 2 lines \(lines 5, 7\)"):
        read_dataset(tmp_path / "d.csv", _model(), partial=False)
    data = read_dataset(tmp_path / "d.csv", _model(), nonfinite="drop", partial=False)
    assert data.num_rows == 10 and data.dropped == {"y2": 2}


def test_problem_box_norm_and_json_round_trip():
    model = _model()
    frame = _frame()
    frame["p"] = np.linspace(1.0, 1.5, len(frame))
    data = read_dataset(frame, model)
    problem = Problem.build(model, data, theta=["p"], noise={"y1": 0.1, "y2": 0.2})
    np.testing.assert_allclose(problem.theta_low, [0.5])
    boxed = Problem.build(model, data, theta=["p"], box="data", margin=0.1)
    np.testing.assert_allclose(boxed.theta_low, [0.95])
    again = Problem.from_json(problem.to_json(), model)
    np.testing.assert_allclose(again.norm.x_std, problem.norm.x_std)
    np.testing.assert_allclose(again.noise_std, [0.1, 0.2])
    with pytest.raises(ValueError, match="missing"):
        Problem.build(model, data, noise={"y1": 0.1})


def test_models_load_specs(tmp_path):
    assert jaxcal.models.load("heat_exchanger").name == "heat_exchanger"
    path = tmp_path / "m.py"
    path.write_text(
        "import jax.numpy as jnp, jaxcal\n"
        "model = jaxcal.Model.from_function(lambda w, t: w * t, conditions=('u',),"
        " parameters={'k': (1.0, 0.0, 2.0)}, outputs=('y',))\n"
    )
    assert jaxcal.models.load(f"{path}:model").parameter_names == ("k",)
    with pytest.raises(ValueError, match="registered"):
        jaxcal.models.load("no_such_model")


def test_a_run_folder_of_the_older_layout_reads_as_the_same_problem():
    from jaxcal.calibrators.methods.policy.loading import run_problem

    model = _model()
    frame = _frame()
    problem = Problem.build(model, read_dataset(frame, model), theta=["p"])
    new = {"problem": problem.to_json(), "model_spec": "unused"}
    rng = problem.input_range._asdict()
    old = {
        "engine": "unused",
        "sensors": list(problem.output_names),
        **{k: v for k, v in problem.to_json().items() if k.startswith("theta")},
        "norm": problem.to_json()["norm"],
        **{k: np.asarray(v).tolist() for k, v in rng.items()},
    }
    a, b = run_problem(new, model), run_problem(old, model)
    assert a.theta_names == b.theta_names and a.output_names == b.output_names
    np.testing.assert_allclose(a.norm.x_std, b.norm.x_std)
    np.testing.assert_allclose(a.input_range.x_high, b.input_range.x_high)
