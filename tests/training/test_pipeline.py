"""The training pipeline: data selection, scores, calibrator, resume and checkpoints.

Runs use the ``smoke`` preset on a small synthetic N-CMAPSS file (no engine needed).
The expensive compilations (training chunk, fleet calibrator) are cached per process
by ``make_components``, so the three runs of the resume test compile them once.
"""

import dataclasses

import chex
import jax
import numpy as np
import pytest
from support.synthetic_file import write_synthetic_ncmapss

from jaxcal.deploy import load_run
from jaxcal.models.turbofan.training import load_calibration_data
from jaxcal.problem import Normalisation
from jaxcal.runs.metrics_log import read_metrics
from jaxcal.training.config import make_train_config, resolve_config
from jaxcal.training.data.train_env import training_env_params
from jaxcal.training.pipeline import ensure_data_file, read_run_data, run_training
from jaxcal.training.scoring.trajectories import theta_rmse, tracking_rmse

# Per-chunk wall-clock fields differ between runs by nature.
TIMING = {"chunk_seconds", "updates_per_s", "env_steps_per_s", "includes_compile",
          "job_seconds", "time_to_target_s"}  # fmt: skip


@pytest.fixture(scope="module")
def data_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "synthetic.h5"
    return write_synthetic_ncmapss(path, dev_units=(1, 2, 3), test_units=(4, 5))


def smoke_config(path, runs_dir, **budget):
    cfg = resolve_config(
        [
            "dataset=ncmapss",
            "preset=smoke",
            f"path={path}",
            "dataset.stride=1",
            f"output.runs_dir={runs_dir}",
            "output.progress=false",
        ]
    )
    return dataclasses.replace(cfg, budget=dataclasses.replace(cfg.budget, **budget))


def quiet(_message):
    pass


def test_data_selection_defaults_and_errors(data_file):
    data = load_calibration_data(str(data_file), theta_margin=0.1)
    # Only HPT_eff_mod varies in T; no observed_sensors attribute: the 14 X_s.
    assert data.problem.theta_names == ("HPT_eff_mod",)
    assert len(data.problem.output_names) == 14
    assert data.train.unit_ids.tolist() == [1, 2] and data.val.unit_ids.tolist() == [3]
    assert data.test.unit_ids.tolist() == [4, 5]
    # Units have 120 + 7 k rows; each split is padded to its longest unit.
    assert data.train.lengths.tolist() == [120, 127] and data.train.x.shape[1] == 127
    assert data.test.x.shape == (2, 127, 14) and data.test.theta.shape == (2, 127, 1)
    dev_theta = np.concatenate(
        [data.train.theta[data.train.mask], data.val.theta[data.val.mask]]
    )
    width = dev_theta.max() - dev_theta.min()
    np.testing.assert_allclose(data.problem.theta_low, dev_theta.min() - 0.1 * width)
    np.testing.assert_allclose(data.problem.theta_high, dev_theta.max() + 0.1 * width)
    chosen = load_calibration_data(
        str(data_file), sensors=("T48", "Nc"), theta=("HPT_eff_mod",), val_units=()
    )
    assert chosen.val is None and chosen.train.x.shape[-1] == 2
    with pytest.raises(ValueError, match="theta must be distinct names"):
        load_calibration_data(str(data_file), theta=("HPT_eff",))
    with pytest.raises(ValueError, match="not dev units"):
        load_calibration_data(str(data_file), val_units=(4,))
    with pytest.raises(ValueError, match="not in X_s_var"):
        load_calibration_data(str(data_file), sensors=("bogus",))


def test_scores_match_hand_computed_values():
    theta_hat = np.array([[[1.0], [2.0], [9.0]]])
    theta = np.array([[[0.0], [0.0], [0.0]]])
    mask = np.array([[True, True, False]])
    pooled, per = theta_rmse(theta_hat, theta, mask)
    assert pooled == pytest.approx(np.sqrt((1 + 4) / 2)) and per.shape == (1,)
    x = np.array([[[0.0, 0.0], [2.0, 4.0], [1.0, 1.0]]])
    xhat = np.array([[[5.0, 5.0], [0.0, 0.0], [0.0, 0.0]]])
    # t = 0 is excluded (x-hat_0 = x_0 by construction); t = 2 is padding.
    pooled, norm, units = tracking_rmse(xhat, x, mask, np.array([1.0, 2.0]))
    np.testing.assert_allclose(units, [2.0, 4.0])
    np.testing.assert_allclose(norm, [2.0, 2.0])
    assert pooled == pytest.approx(2.0)


def test_config_presets_aliases_and_errors(tmp_path):
    paper = resolve_config(["preset=paper", "agent=lac"])
    assert paper.agent_name == "lac" and paper.agent.actor_lr == 1e-4
    assert paper.agent.initial_entropy_temperature == 2.0
    tuned = resolve_config(["agent=sac", "agent.gamma=0.5", "seed=3"])
    assert tuned.agent_name == "sac" and tuned.agent.gamma == 0.5
    assert tuned.run_name == "cmapss-sac-physics-inc-s3"
    # the default: a feedback policy through F; absolute: the paper's formulation
    default = resolve_config([])
    assert default.dynamics == "physics" and default.env.action == "increment"
    assert default.env.cost == "log" and default.agent.smoothness_threshold == 0.1
    assert default.budget.target_theta_rmse == 2.5e-4
    absolute = resolve_config(["preset=absolute"])
    assert absolute.dynamics == "surrogate" and absolute.env.action == "absolute"
    assert absolute.env.cost == "squared"
    assert absolute.agent.smoothness_threshold == 0.002
    assert absolute.run_name == "cmapss-clac-surrogate-s0-absolute"
    smoke = resolve_config(["preset=smoke"])
    assert smoke.dynamics == "surrogate" and smoke.env.action == "absolute"
    with pytest.raises(ValueError, match="env.action"):
        resolve_config(["env.action=relative"])
    cfg = resolve_config(["dataset=ncmapss", "path=x.h5", "theta=LPT_eff_mod"])
    assert cfg.dataset.path == "x.h5" and cfg.theta == ("LPT_eff_mod",)
    with pytest.raises(ValueError, match="valid keys.*budget.*dynamics"):
        resolve_config(["bogus=1"])
    with pytest.raises(ValueError, match="unknown preset"):
        resolve_config(["preset=huge"])
    with pytest.raises(ValueError, match="unknown dataset"):
        make_train_config("nope")
    with pytest.raises(ValueError, match="path=<file.h5>"):
        ensure_data_file(resolve_config(["dataset=ncmapss"]), log=quiet)


@pytest.fixture(scope="module")
def resumed_and_straight(data_file, tmp_path_factory):
    runs = tmp_path_factory.mktemp("runs")
    cfg = smoke_config(data_file, runs, num_chunks=2, ckpt_every=1, eval_every=1)
    interrupted = dataclasses.replace(
        cfg, output=dataclasses.replace(cfg.output, name="interrupted")
    )
    run_training(interrupted, log=quiet)
    resumed = dataclasses.replace(
        interrupted, budget=dataclasses.replace(cfg.budget, num_chunks=4)
    )
    final_resumed = run_training(resumed, log=quiet)
    straight = dataclasses.replace(
        resumed, output=dataclasses.replace(cfg.output, name="straight")
    )
    final_straight = run_training(straight, log=quiet)
    return runs, resumed, final_resumed, final_straight


def test_resume_reproduces_the_uninterrupted_run(resumed_and_straight):
    runs, _, final_resumed, final_straight = resumed_and_straight
    records = {
        name: [
            {k: v for k, v in r.items() if k not in TIMING}
            for r in read_metrics(runs / name / "metrics.jsonl")
        ]
        for name in ("interrupted", "straight")
    }
    assert [r["step"] for r in records["interrupted"]] == [1, 2, 3, 4]
    assert records["interrupted"] == records["straight"]
    assert final_resumed["test"] == final_straight["test"]
    assert final_resumed["num_updates"] == final_straight["num_updates"] > 0
    assert final_resumed["selected_chunk"] == final_straight["selected_chunk"]
    for which in ("selected", "last"):
        params = [
            load_run(runs / name, which=which).params
            for name in ("interrupted", "straight")
        ]
        chex.assert_trees_all_equal(params[0], params[1])


def test_checkpointed_policy_round_trips(resumed_and_straight, data_file):
    runs, _, final_resumed, _ = resumed_and_straight
    run = load_run(runs / "straight", which="last")
    assert run.step == 4 and run.problem.theta_names == ("HPT_eff_mod",)
    assert load_run(runs / "straight").step == final_resumed["selected_chunk"]
    chex.assert_tree_all_finite(run.params)
    # Rescoring the restored policy gives the scores computed in memory at the end.
    from jaxcal.cli.evaluate import evaluate_run

    report = evaluate_run(str(runs / "straight"), repeats=3)
    assert report["theta_rmse"] == pytest.approx(final_resumed["test"]["theta_rmse"])
    assert report["tracking_rmse_norm"] == pytest.approx(
        final_resumed["test"]["tracking_rmse_norm"]
    )
    # The surrogate D restored from its checkpoint is the fitted one.
    leaves = jax.tree.leaves(run.params.dyn_params)
    assert leaves and all(np.all(np.isfinite(np.asarray(v))) for v in leaves)


def test_a_run_carries_one_normalisation(resumed_and_straight):
    """The normalisation is made once, when the run's data are read: in the run's
    dtype (float32 here) over the training units' valid rows, stored as float64
    copies. The environment, ``data.json`` and the deployed policy hold it bit for
    bit: nothing recomputes or replaces it."""
    runs, resumed, _, _ = resumed_and_straight
    data = read_run_data(resumed)
    norm, train = data.problem.norm, data.train
    rows = train.mask
    w, x = train.w.astype(np.float32)[rows], train.x.astype(np.float32)[rows]
    for made, own in zip(norm, Normalisation.of(w, x, dtype=None), strict=True):
        assert made.dtype == np.float64 and own.dtype == np.float32
        np.testing.assert_array_equal(made, own.astype(np.float64))
    env = training_env_params(train, data.problem, None, np.float32, "surrogate")
    run = load_run(runs / "straight")
    for name, value in norm._asdict().items():
        cast = value.astype(np.float32)  # exact: a float32 value stored as float64
        np.testing.assert_array_equal(cast.astype(np.float64), value)
        for held in (getattr(env, name), getattr(run.params, name)):
            assert held.dtype == np.float32
            np.testing.assert_array_equal(np.asarray(held), cast)
        np.testing.assert_array_equal(getattr(run.problem.norm, name), value)
    # the provisional noise stays 1 % of each output's float64 spread
    np.testing.assert_array_equal(
        data.problem.noise_std, 0.01 * np.asarray(train.x, np.float64)[rows].std(0)
    )


def test_a_different_config_under_the_same_name_is_an_error(resumed_and_straight):
    _, resumed, _, _ = resumed_and_straight
    other = dataclasses.replace(
        resumed, agent=dataclasses.replace(resumed.agent, actor_lr=0.123)
    )
    with pytest.raises(ValueError, match=r"different config.*agent.actor_lr"):
        run_training(other, log=quiet)


def test_resume_without_buffer_refills_it(data_file, tmp_path):
    cfg = smoke_config(data_file, tmp_path, num_chunks=2, ckpt_every=1, eval_every=0)
    cfg = dataclasses.replace(
        cfg, output=dataclasses.replace(cfg.output, save_buffer=False, name="nobuf")
    )
    run_training(cfg, log=quiet)
    longer = dataclasses.replace(
        cfg, budget=dataclasses.replace(cfg.budget, num_chunks=3)
    )
    final = run_training(longer, log=quiet)
    records = read_metrics(tmp_path / "nobuf" / "metrics.jsonl")
    # The restored buffer is empty: 100 transitions per chunk, updates wait for 100.
    assert [r["buffer_size"] for r in records] == [100, 200, 100]
    assert final["chunks"] == 3 and np.isfinite(final["test"]["theta_rmse"])
