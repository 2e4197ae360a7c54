"""Labelled units simulated from the model (jaxcal.training.data.simulated)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal
from jaxcal.data.padded import Padded
from jaxcal.training.data.calibration import training_problem
from jaxcal.training.data.sim_paths import drift_paths, estimated_drifts, theta_paths
from jaxcal.training.data.simulated import parse_noise, simulate_units


def _fn(w, theta):
    return jnp.stack([theta[0] * w[0], theta[1] + w[0] * w[1]])


MODEL = jaxcal.Model.from_function(
    _fn,
    conditions=("a", "b"),
    parameters={"p": (1.0, 0.5, 2.0), "q": (0.0, -1.0, 1.0)},
    outputs=("y1", "y2"),
    name="lin",
)


def _units(num_units=6, rows=50, seed=0):
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.5, 1.5, (num_units, rows, 2))
    lengths = np.full(num_units, rows, np.int32)
    lengths[0] = rows // 2
    x = np.zeros((num_units, rows, 2))
    return Padded(w, x, None, lengths, np.arange(1, num_units + 1))


def test_theta_paths_stay_in_the_box_monotone_and_some_constant():
    low, high = np.array([0.5, -1.0]), np.array([2.0, 1.0])
    lengths = np.array([30] * 200)
    paths = theta_paths(jax.random.key(0), low, high, lengths, 40, 0.25)
    assert paths.shape == (200, 40, 2)
    assert np.all(paths >= low - 1e-12) and np.all(paths <= high + 1e-12)
    steps = np.diff(paths, axis=1)
    assert np.all((steps >= -1e-12).all(1) | (steps <= 1e-12).all(1))  # monotone
    constant = np.all(np.abs(steps) < 1e-12, axis=(1, 2))
    assert 0.1 < constant.mean() < 0.4
    np.testing.assert_allclose(paths[:, 30:], paths[:, 29:30].repeat(10, 1))


def test_simulated_units_are_the_model_plus_the_problems_noise():
    units = _units()
    problem = training_problem(
        MODEL, units, ("p", "q"), ("y1", "y2"), MODEL.nominal, *MODEL.bounds
    ).with_noise(np.array([0.01, 0.2]), "given")
    sim, clean = simulate_units(problem, units, jax.random.key(1), copies=2)
    assert sim.x.shape == (12, 50, 2) and np.all(sim.unit_ids < 0)
    mask = np.asarray(sim.mask)
    expect = np.asarray(jax.vmap(jax.vmap(_fn))(sim.w, sim.theta))
    np.testing.assert_allclose(clean[mask], expect[mask], rtol=1e-6)
    noise = (sim.x - clean)[mask]
    np.testing.assert_allclose(noise.std(axis=0), [0.01, 0.2], rtol=0.1)
    assert np.all(sim.x[~mask] == 0.0)


def test_estimated_drifts_follow_the_units_own_slow_drift():
    """The UKF's theta on units made along a drift, fitted by a quadratic: close to
    that drift (not to paths across the box), held past a unit's end; copies
    simulated along the drifts take them in turn."""
    units = _units(num_units=3, rows=120)
    problem = training_problem(
        MODEL, units, ("p", "q"), ("y1", "y2"), MODEL.nominal, *MODEL.bounds
    ).with_noise(np.array([0.01, 0.01]), "given")
    coef = np.array([[[1.1, -0.2], [0.0, 0.1], [0.3, 0.0]]])  # [1, 3, P]
    sim, _ = simulate_units(problem, units, jax.random.key(2), drifts=coef)
    s = np.minimum(np.arange(120)[None] / (units.lengths[:, None] - 1.0), 1.0)
    truth = np.stack([1.1 + 0.3 * s**2, -0.2 + 0.1 * s], -1)
    np.testing.assert_allclose(sim.theta, truth, rtol=1e-6)
    drifts = estimated_drifts(problem, sim._replace(theta=None))
    paths = drift_paths(problem, drifts, units.lengths, 120)
    late = np.asarray(units.mask) & (np.arange(120) >= 20)[None]  # after start-up
    err = np.abs(paths - truth)[late]
    assert err.max(0).tolist() < [0.03, 0.03], err.max(0)
    np.testing.assert_array_equal(paths[0, 60:], paths[0, 59:60].repeat(60, 0))
    twice, _ = simulate_units(
        problem, units, jax.random.key(3), copies=2, drifts=drifts
    )
    np.testing.assert_allclose(twice.theta[3:], paths, rtol=1e-6)
    # a unit of fewer than three rows the UKF used shows no drift: left out
    short = sim.lengths.copy()
    short[1] = 2
    kept = estimated_drifts(problem, sim._replace(lengths=short, theta=None))
    np.testing.assert_allclose(kept, drifts[[0, 2]], rtol=1e-9)


def test_parse_noise_pairs_or_ordered_values_else_a_clear_error():
    names = ("y1", "y2")
    np.testing.assert_allclose(parse_noise(("y2:0.5", "y1:0.1"), names), [0.1, 0.5])
    np.testing.assert_allclose(parse_noise(("0.1", "0.5"), names), [0.1, 0.5])
    assert parse_noise((), names) is None
    for bad, match in (
        (("y1:0.1",), "misses"),
        (("y3:0.1", "y1:1", "y2:1"), "unknown"),
        (("0.1",), "one std per used output"),
        (("0.1", "x"), "not a number"),
        (("0.1", "-1"), "finite and > 0"),
    ):
        with pytest.raises(ValueError, match=match):
            parse_noise(bad, names)


def test_any_model_default_preset_uses_labels_to_score_only():
    import dataclasses

    from jaxcal.training.components import (
        agent_config,
        env_config,
        uses_filter,
        uses_gauss_newton,
    )
    from jaxcal.training.config import ANY_MODEL_COPIES, make_train_config

    cfg = make_train_config("file", "default")
    assert cfg.dataset.labels == "score" and cfg.env.start == "prior"
    assert cfg.simulate.train == "both" and cfg.simulate.band == "simulated"
    assert cfg.simulate.copies == ANY_MODEL_COPIES and cfg.budget.select == "sim_theta"
    assert cfg.simulate.paths == "data" and cfg.env.gauss_newton == "filter"
    # "filter": the one-sample Gauss-Newton step where the outputs determine theta,
    # as "auto", and the filter's step (the untrained action: gain 1) everywhere
    assert uses_gauss_newton(cfg.env, 3, 2) and uses_gauss_newton(cfg.env, 2, 2)
    assert uses_filter(cfg.env) and cfg.env.filter_gain == 1.0
    assert cfg.env.filter_q == 0.01  # the UKF's default random walk
    env_cfg = env_config(cfg, 2, 3, 2)
    assert env_cfg.gn_filter and env_cfg.observation_size == 3 + 1 + 2 + 2 + 2 + 2 + 1
    # the filter's step sits just before the age: the actor's prior reads it there
    assert agent_config(cfg, env_cfg).actor_prior == (13 - 2 - 1, 1.0)
    # the battery: one voltage for R0 and Q: no one-sample step, the filter's only
    assert not uses_gauss_newton(cfg.env, 1, 2)
    battery = env_config(cfg, 2, 1, 2)
    assert battery.gn_filter and not battery.gauss_newton
    assert battery.observation_size == 1 + 1 + 2 + 2 + 2 + 1
    assert agent_config(cfg, battery).actor_prior == (9 - 2 - 1, 1.0)
    auto_env = dataclasses.replace(cfg.env, gauss_newton="auto")
    auto = dataclasses.replace(cfg, env=auto_env)
    assert not env_config(auto, 2, 3, 2).gn_filter  # the runs trained before it
    assert agent_config(auto, env_config(auto, 2, 3, 2)).actor_prior is None
    # the turbofan data sets and the other presets keep their formulation
    cmapss = make_train_config("cmapss", "default")
    assert cmapss.dataset.labels == "use" and cmapss.simulate.train == "data"
    assert cmapss.simulate.paths == "box" and not uses_gauss_newton(cmapss.env, 9, 2)
    assert make_train_config("file", "smoke").simulate.train == "data"


def test_table_data_with_labels_to_score_only(tmp_path):
    import pandas as pd

    from jaxcal.training.data.tables import load_table_data

    rng = np.random.default_rng(0)
    rows = []
    for unit in range(1, 5):
        w = rng.uniform(0.5, 1.5, (20, 2))
        theta = np.array([1.2, 0.1])
        x = np.asarray(jax.vmap(_fn, (0, None))(jnp.asarray(w), jnp.asarray(theta)))
        rows.append(
            pd.DataFrame(
                {"unit": unit, "time": np.arange(20), "a": w[:, 0], "b": w[:, 1],
                 "y1": x[:, 0], "y2": x[:, 1], "p": theta[0], "q": theta[1]}
            )
        )  # fmt: skip
    path = tmp_path / "lin.csv"
    pd.concat(rows).to_csv(path, index=False)
    used = load_table_data(path, MODEL, theta=("p", "q"))
    assert used.info["box"] == "labelled range"
    scored = load_table_data(path, MODEL, theta=("p", "q"), use_labels=False)
    assert scored.info["box"].startswith("model bounds")
    np.testing.assert_array_equal(scored.problem.theta_low, MODEL.bounds[0])
    np.testing.assert_array_equal(scored.problem.theta_base, MODEL.nominal)
    assert scored.test.theta is not None  # still there, to score


def test_an_incremental_policy_starts_at_theta_start_else_the_box_centre():
    import dataclasses

    from jaxcal.calibrators.methods.policy.calibrator import (
        IncrementPolicyParams,
        StartedIncrementPolicyParams,
        make_policy_calibrator,
    )

    # the layout of every incremental run saved before theta_start existed
    # (the arrays a checkpoint holds; max_increment, gauss_newton, gn_filter and
    # filter_q are static, and x_noise, the filter's, is None there: no leaf)
    fields = dataclasses.fields(IncrementPolicyParams)
    leaves = [f.name for f in fields if f.metadata.get("pytree_node", True)]
    static = [f.name for f in fields if not f.metadata.get("pytree_node", True)]
    assert leaves[-2:] == ["step_ref", "x_noise"] and "theta_start" not in leaves
    assert next(f for f in fields if f.name == "x_noise").default is None
    # nor after it: a started policy's last leaf stays its start (the filter's
    # output states, tune.bias, are a class of their own)
    started = dataclasses.fields(StartedIncrementPolicyParams)
    assert [f.name for f in started][-1] == "theta_start"
    assert static == [
        "max_increment",
        "gauss_newton",
        "gn_filter",
        "filter_q",
        "filter_whole",
        "filter_prior_std",
        "filter_adapt",
    ]
    fields = dict(
        actor=None, dyn_params=None, w_mean=jnp.zeros(2), w_std=jnp.ones(2),
        x_mean=jnp.zeros(2), x_std=jnp.ones(2), theta_low=jnp.array([0.5, -1.0]),
        theta_high=jnp.array([2.0, 1.0]), step_ref=jnp.ones(2),
    )  # fmt: skip
    for params, expect in (
        (IncrementPolicyParams(**fields), [1.25, 0.0]),
        (StartedIncrementPolicyParams(**fields, theta_start=jnp.ones(2)), [1.0, 1.0]),
    ):
        cal = make_policy_calibrator(None, lambda p, w, x, th: x, params)
        state = cal.init(None, jnp.ones(2), jnp.zeros(2))
        np.testing.assert_allclose(state.theta, expect)


def test_tuning_and_guard_units_are_labelled_and_the_clean_twin_is_effect_free():
    """tune's units (the data's drifts and the box) carry labels; the guard's clean
    twin is the selection units without their effects: same theta and noise."""
    import dataclasses

    from jaxcal.training.config import make_train_config
    from jaxcal.training.data.calibration import CalibrationData
    from jaxcal.training.data.simulated import Simulations

    units = _units()
    problem = training_problem(
        MODEL, units, ("p", "q"), ("y1", "y2"), MODEL.nominal, *MODEL.bounds
    )
    data = CalibrationData(
        problem=problem, train=units, val=None, test=units, info={}
    )  # fmt: skip
    cfg = make_train_config("file", "default")
    cfg = dataclasses.replace(
        cfg, noise=("0.01", "0.02"),
        simulate=dataclasses.replace(cfg.simulate, effects=0.5, band_copies=2,
                                     paths="box"),
    )  # fmt: skip
    sims = Simulations(cfg, data, log=lambda _: None)
    tuning = sims.tuning_units()
    assert tuning.theta is not None and tuning.theta.shape[0] == 2 * 2 * 6
    guards = sims.guard_units()
    assert len(guards) == 3 and all(g.theta is not None for g in guards)
    select, twin = sims.selection_units(), guards[0]
    np.testing.assert_array_equal(select.theta, twin.theta)
    differs = np.any(select.x != twin.x, axis=(1, 2))
    assert 0 < differs.sum() < len(differs)  # the effects' share, the rest equal
