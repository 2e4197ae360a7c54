"""The comparison machinery of ``jaxcal.paper`` on a toy linear "engine".

A linear model stands in for the turbofan (same interface as ``Engine.evaluate``: 28
sensors from 4 conditions and 10 health modifiers), so the UKF and least-squares
methods, the model perturbations of the robustness tables, the scoring and the report
are exercised in seconds.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct
from support.keys import has_prng_key
from support.paper_problem import paper_problem

from jaxcal.calibrators.interface import Calibrator, CalStepOutput
from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig
from jaxcal.data.padded import Padded
from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES, SENSOR_NAMES
from jaxcal.paper.compare import (
    evaluate_method,
    limit_units,
    measure_latency,
    stacked,
)
from jaxcal.paper.methods import (
    evaluation_key,
    model_method,
    paper_config,
    perturb_output,
    with_step_key,
)
from jaxcal.paper.report import write_report
from jaxcal.paper.simulate import gather_units, subset_units
from jaxcal.problem import Problem

SENSORS = ("T24", "T30", "T48", "Nc")
THETA = ("HPT_eff_mod",)


@struct.dataclass
class LinearEngine:
    """x = base + A theta + B w_n: a stand-in with the engine's evaluate signature."""

    base: jax.Array  # [28]
    a: jax.Array  # [28, 10]
    b: jax.Array  # [28, 4]

    def evaluate(self, w, theta):
        w_n = (w - jnp.array([20_000.0, 0.5, 60.0, 500.0])) / jnp.array(
            [5_000.0, 0.1, 10.0, 20.0]
        )
        x = self.base + theta @ self.a.T + w_n @ self.b.T
        return x, None


def _engine() -> LinearEngine:
    rng = np.random.default_rng(0)
    n = len(SENSOR_NAMES)
    return LinearEngine(
        base=jnp.asarray(rng.uniform(100, 1000, n)),
        a=jnp.asarray(rng.normal(0, 200, (n, len(HEALTH_NAMES)))),
        b=jnp.asarray(rng.normal(0, 5, (n, 4))),
    )


def _units(engine, lengths=(30, 22), seed=1) -> Padded:
    rng = np.random.default_rng(seed)
    num_steps = max(lengths)
    w = np.stack(
        [
            np.column_stack(
                [
                    rng.uniform(15_000, 25_000, num_steps),
                    rng.uniform(0.4, 0.6, num_steps),
                    rng.uniform(50, 70, num_steps),
                    rng.uniform(480, 520, num_steps),
                ]
            )
            for _ in lengths
        ]
    )
    theta = (
        -np.linspace(0.002, 0.004, num_steps)[None, :, None]
        * np.array([1.0, 0.7])[:, None, None]
    )
    full = np.zeros(w.shape[:2] + (len(HEALTH_NAMES),))
    full[..., HEALTH_NAMES.index("HPT_eff_mod")] = theta[..., 0]
    x_full, _ = engine.evaluate(jnp.asarray(w), jnp.asarray(full))
    cols = [SENSOR_NAMES.index(s) for s in SENSORS]
    return Padded(
        w=w,
        x=np.asarray(x_full)[..., cols],
        theta=theta,
        lengths=np.array(lengths, np.int32),
        unit_ids=np.array([7, 8], np.int64),
    )


def _problem(units: Padded) -> Problem:
    x = units.x[units.mask]
    return paper_problem("toy", SENSORS, THETA, [-0.02], [0.002], x.mean(0), x.std(0))


@pytest.fixture(scope="module")
def toy():
    engine = _engine()
    units = _units(engine)
    return engine, units, _problem(units)


def test_perturb_output_is_exact_when_off_and_scales_when_on():
    x = jnp.array([100.0, 2.0, -3.0])
    std = jnp.array([1.0, 0.5, 2.0])
    key = jax.random.key(0)
    one, zero = jnp.ones(()), jnp.zeros(())
    assert jnp.array_equal(perturb_output(x, key, one, zero, std), x)
    np.testing.assert_allclose(perturb_output(x, key, 1.02 * one, zero, std), 1.02 * x)
    keys = jax.random.split(key, 4000)
    noisy = jax.vmap(lambda k: perturb_output(x, k, one, 0.1 * one, std))(keys)
    np.testing.assert_allclose(np.std(noisy - x, axis=0), 0.1 * std, rtol=0.1)


def test_evaluation_key_is_a_function_of_the_inputs():
    key = jax.random.key(3)
    a = evaluation_key(key, jnp.array([1.0, 2.0]), jnp.array([0.1]))
    same = evaluation_key(key, jnp.array([1.0, 2.0]), jnp.array([0.1]))
    other = evaluation_key(key, jnp.array([1.0, 2.0]), jnp.array([0.2]))
    data = jax.random.key_data
    assert np.array_equal(data(a), data(same))
    assert not np.array_equal(data(a), data(other))


def test_with_step_key_needs_a_key_and_draws_fresh_noise_every_step():
    def make(key):
        def init(_, w0, x0):
            return jnp.zeros(())

        def step(state, w, x):
            theta = jax.random.normal(key, (1,))
            return state + 1, CalStepOutput(theta=theta, xhat=x)

        return Calibrator(init, step)

    cal = with_step_key(make)
    with pytest.raises(ValueError, match="needs a PRNG key"):
        cal.init(None, jnp.zeros(4), jnp.zeros(2))
    state = cal.init(jax.random.key(0), jnp.zeros(4), jnp.zeros(2))
    state, first = cal.step(state, jnp.zeros(4), jnp.zeros(2))
    _, second = cal.step(state, jnp.zeros(4), jnp.zeros(2))
    assert first.theta != second.theta
    again = cal.step(
        cal.init(jax.random.key(0), jnp.zeros(4), jnp.zeros(2)),
        *[jnp.zeros(4), jnp.zeros(2)],
    )[1]
    assert again.theta == first.theta


def _model_based(engine, problem):
    """Every registered method on the model, on the toy model with the paper's
    settings (least squares: a small window, fast)."""
    from jaxcal.calibrators.methods import REGISTRY
    from jaxcal.calibrators.ukf import UKFConfig

    ls = LeastSquaresConfig(window=4)
    methods = tuple(
        model_method(engine, problem, paper_config(m, UKFConfig(), ls), m.label)
        for m in REGISTRY.values()
        if m.on_model
    )
    assert [m.name for m in methods][:2] == ["UKF", "LS"]
    assert "EKF" in [m.name for m in methods], "the EKF is a registered method on F"
    return methods


def test_ukf_and_least_squares_recover_theta_and_suffer_from_model_bias(toy):
    engine, units, problem = toy
    with jax.enable_x64(True):
        for method in _model_based(engine, problem):
            clean = evaluate_method(method, units, problem)
            biased = evaluate_method(method, units, problem, bias=1.02)
            noisy = evaluate_method(method, units, problem, noise_sigma=0.1, seed=1)
            noisy_again = evaluate_method(
                method, units, problem, noise_sigma=0.1, seed=1
            )
            assert clean.scores["theta_rmse"] < 2e-4, method.name
            assert biased.scores["theta_rmse"] > 10 * clean.scores["theta_rmse"]
            assert noisy.scores["theta_rmse"] > clean.scores["theta_rmse"]
            np.testing.assert_array_equal(noisy.theta, noisy_again.theta)
            assert clean.scores["tracking_rmse_norm"] < 0.05
            assert set(clean.scores["theta_rmse_per_unit"]) == {"7", "8"}
            assert clean.scores["num_samples"] == 52
            # the std in the method's aux reaches the scores
            assert 0.0 <= clean.scores["coverage90"] <= 1.0
            assert clean.scores["theta_std_median"] > 0
            # padded rows hold the last valid estimate
            assert clean.theta[1, 21] == clean.theta[1, 29]


def test_limit_units_takes_a_seeded_subset_and_cuts_trajectories(toy):
    _, units, _ = toy
    cut = limit_units(units, max_steps=10)
    assert cut.x.shape[1] == 10 and cut.lengths.tolist() == [10, 10]
    one = limit_units(units, max_units=1, seed=0)
    assert one.unit_ids.tolist() == limit_units(units, max_units=1).unit_ids.tolist()
    assert len(one.unit_ids) == 1 and one.x.shape[1] == one.lengths[0]
    values, starts = stacked(units.theta, units.mask)
    assert values.shape == (52, 1) and starts.tolist() == [0, 30]


def test_gather_and_subset_units_keep_whole_units(toy):
    _, units, _ = toy
    picked = gather_units([units, None], [8, 7])
    assert picked.unit_ids.tolist() == [8, 7] and picked.lengths.tolist() == [22, 30]
    np.testing.assert_array_equal(picked.x[1], units.x[0])
    with pytest.raises(ValueError, match=r"unit\(s\) \[99\]"):
        gather_units([units], [99])
    small = subset_units(jax.random.key(0), units, max_samples=25)
    assert len(small.unit_ids) == 1 and small.x.shape[1] == small.lengths[0]


def _eval(theta, tracking, method):
    return {
        "dataset": "ds1",
        "method": method,
        "theta_rmse": theta,
        "tracking_rmse_norm": tracking,
        "theta_rmse_per_param": {"HPT_eff_mod": theta},
        "theta_rmse_per_unit": {"7": theta},
        "units": [7],
        "num_samples": 10,
        "batched_samples_per_s": 1000.0,
        "info": {},
        "seconds": 1.0,
        "estimate_s": 2.0,
    }


def test_report_shows_losses_and_dashes_for_missing_results(tmp_path):
    steps = {
        "eval-ds1-UKF-clean": _eval(2e-4, 0.01, "UKF"),
        "eval-ds1-CLAC-clean": _eval(4e-4, 0.5, "CLAC"),
    }
    path = write_report(
        tmp_path / "REPORT.md", steps, preset="test", description="toy",
        seed=0, command="test", wall_seconds=1.0,
    )  # fmt: skip
    text = path.read_text()
    for heading in ("## 1.", "## 2.", "## 3.", "## 4.", "## 5.", "## 6.", "## 7."):
        assert heading in text
    assert "| UKF on F | 2.00e-04 | 3.42e-04 | – | 3.51e-03 |" in text
    assert "Dataset #1 CLAC / UKF: ours **2.00**, paper 0.96" in text
    assert "UKF on F 2.00e-04 < CLAC 4.00e-04 (x2)" in text
    assert "Dataset #1 tracking RMSE: UKF on F" in text
    assert (tmp_path / "results.json").is_file()


def _stream_thetas(cal, units):
    step = jax.jit(cal.step)
    w, x = units.w[0, : units.lengths[0]], units.x[0, : units.lengths[0]]
    state = cal.init(jax.random.key(0), jnp.asarray(w[0]), jnp.asarray(x[0]))
    rows = []
    for t in range(len(w)):
        state, out = step(state, jnp.asarray(w[t]), jnp.asarray(x[t]))
        rows.append(np.asarray(out.theta))
    return np.stack(rows), state


def test_deployed_form_is_the_clean_method_without_its_noise_key(toy):
    engine, units, problem = toy
    with jax.enable_x64(True):
        for method in _model_based(engine, problem):
            one, zero = jnp.ones((), jnp.float64), jnp.zeros((), jnp.float64)
            scored, scored_state = _stream_thetas(method.build(one, zero), units)
            deployed, deployed_state = _stream_thetas(method.deploy(), units)
            assert has_prng_key(scored_state) and not has_prng_key(deployed_state)
            # the unperturbed model is the same function bit for bit
            np.testing.assert_array_equal(deployed, scored)
            assert np.ptp(deployed, axis=0).max() > 1e-4  # theta moved
            record = measure_latency(method, units, repeats=3)
            assert record["deploy_form"] and not record["stream_form"]
            other = measure_latency(
                method, units, repeats=3, calibrator=method.build(one, zero)
            )
            assert not other["deploy_form"]
