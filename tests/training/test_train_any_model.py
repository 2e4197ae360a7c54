"""Training, evaluation and deployment of a policy on a model that is not a turbofan.

The model is defined here, as a user would: a plain JAX function through
``jaxcal.Model.from_function``, loaded by the command line as ``<this file>:MODEL``.
"""

import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.calibrators.uncertainty.conformal import load_band
from jaxcal.cli.evaluate import main as evaluate_main
from jaxcal.cli.train import format_final
from jaxcal.cli.train import main as train_main
from jaxcal.deploy import StreamingCalibrator
from jaxcal.training.data.tables import hold_out_units, load_table_data


def _toy(w, theta):
    """Two conditions (a, b), two parameters (p, q) -> three outputs."""
    a, b = w[0], w[1]
    p, q = theta[0], theta[1]
    return jnp.stack([p * a + q * b, p * q + 0.5 * a, p - q * a * b])


MODEL = jaxcal.Model.from_function(
    _toy,
    conditions={"a": "m", "b": "s"},
    parameters={"p": (1.0, 0.5, 2.0, "-"), "q": (0.5, 0.1, 1.0, "-")},
    outputs=("y1", "y2", "y3"),
    name="toy",
)
SPEC = f"{__file__}:MODEL"
NUM_UNITS, NUM_ROWS = 7, 40


def _frame(seed: int = 0, labels: bool = True) -> pd.DataFrame:
    """7 units of 40 rows: random conditions, slowly drifting p and q."""
    rng = np.random.default_rng(seed)
    rows = []
    for unit in range(1, NUM_UNITS + 1):
        t = np.arange(NUM_ROWS)
        a, b = rng.uniform(0.5, 1.5, NUM_ROWS), rng.uniform(0.2, 1.0, NUM_ROWS)
        p = 1.0 + 0.1 * unit / NUM_UNITS + 0.002 * t
        q = 0.4 + 0.05 * unit / NUM_UNITS + 0.001 * t
        x = np.array(
            [np.asarray(_toy(jnp.array(wi), jnp.array(th))) for wi, th in zip(
                np.stack([a, b], 1), np.stack([p, q], 1), strict=True
            )]
        )  # fmt: skip
        x = x + 1e-3 * rng.standard_normal(x.shape)
        cols = {"unit": unit, "time": t, "a": a, "b": b}
        cols.update({f"y{i + 1}": x[:, i] for i in range(3)})
        if labels:
            cols.update(p=p, q=q)
        rows.append(pd.DataFrame(cols))
    return pd.concat(rows, ignore_index=True)


@pytest.fixture(scope="module")
def csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("toy") / "toy.csv"
    _frame().to_csv(path, index=False)
    return path


def _argv(csv, runs, *extra):
    return [
        f"model={SPEC}",
        f"data={csv}",
        "theta=p,q",
        "preset=smoke",
        f"output.runs_dir={runs}",
        "output.progress=false",
        *extra,
    ]


@pytest.fixture(scope="module")
def trained(csv, tmp_path_factory):
    runs = tmp_path_factory.mktemp("runs")
    assert train_main(_argv(csv, runs, "name=toy")) == 0
    return runs / "toy"


def test_hold_out_units_without_a_split_column():
    units = list(range(1, 11))
    train, val, test = hold_out_units(units, None, None, 0.2, 0.15, "f.csv")
    assert test == [9, 10] and val == [8] and train == list(range(1, 8))
    train, val, test = hold_out_units(units, [1], [2, 3], 0.2, 0.15, "f.csv")
    assert test == [1] and val == [2, 3] and 1 not in train and 2 not in train
    with pytest.raises(ValueError, match="at least 3"):
        hold_out_units([1, 2], None, None, 0.2, 0.15, "f.csv")
    with pytest.raises(ValueError, match=r"test_units=\[42\]: not units"):
        hold_out_units(units, [42], None, 0.2, 0.15, "f.csv")


def test_table_data_splits_box_and_problem(csv, tmp_path):
    data = load_table_data(csv, MODEL, theta=("p", "q"))
    assert data.info["units"] == {"train": [1, 2, 3, 4, 5], "val": [6], "test": [7]}
    assert data.train.w.shape == (5, NUM_ROWS, 2) and data.test.theta.shape[-1] == 2
    # labelled data: the box is the train+val range widened by 10 % on each side
    assert data.info["box"] == "labelled range"
    frame = _frame()
    dev = frame[frame.unit <= 6]
    width = dev.p.max() - dev.p.min()
    assert data.problem.theta_low[0] == pytest.approx(dev.p.min() - 0.1 * width)
    assert data.problem.output_names == ("y1", "y2", "y3")
    # a split column is used as it is
    split = frame.assign(split=np.where(frame.unit <= 2, "test", "train"))
    split.to_csv(tmp_path / "split.csv", index=False)
    data = load_table_data(tmp_path / "split.csv", MODEL, val_units=(7,))
    assert data.info["units"] == {"train": [3, 4, 5, 6], "val": [7], "test": [1, 2]}
    # without labels the box is the model's bounds
    _frame(labels=False).to_csv(tmp_path / "nolabel.csv", index=False)
    data = load_table_data(tmp_path / "nolabel.csv", MODEL, test_units=(1, 2))
    assert data.info["box"] == "model bounds" and data.train.theta is None
    np.testing.assert_array_equal(data.problem.theta_low, [0.5, 0.1])


def test_train_evaluate_deploy_and_calibrate_a_non_turbofan_run(trained, csv, capsys):
    stored = json.loads((trained / "data.json").read_text())
    assert stored["model_spec"].endswith("test_train_any_model.py:MODEL")
    assert stored["problem"]["theta_names"] == ["p", "q"]
    final = json.loads((trained / "final.json").read_text())
    assert final["model"] == "toy" and final["test_units"] == [7]
    assert np.isfinite(final["test"]["theta_rmse"])
    capsys.readouterr()
    assert evaluate_main([f"run={trained}", "repeats=2"]) == 0
    assert "theta RMSE" in capsys.readouterr().out
    assert evaluate_main([f"run={trained}", f"data={csv}", "repeats=2"]) == 0
    report = json.loads((trained / "evaluate_toy.json").read_text())
    assert report["units"] == list(range(1, NUM_UNITS + 1))
    cal = StreamingCalibrator(trained)
    assert cal.conditions == ("a", "b") and cal.sensors == ("y1", "y2", "y3")
    frame = _frame()
    theta = cal.step(frame.loc[0, ["a", "b"]], frame.loc[0, ["y1", "y2", "y3"]])
    assert theta.shape == (2,) and cal.last_valid
    result = jaxcal.calibrate(
        MODEL, csv, method="policy", theta=["p", "q"], run=trained
    )
    assert result.theta.shape == (len(frame), 2) and result.valid.all()
    low, high = stored["problem"]["theta_low"], stored["problem"]["theta_high"]
    assert np.all((result.theta >= low) & (result.theta <= high))


def test_physics_dynamics_on_unlabelled_data(tmp_path):
    path = tmp_path / "nolabel.csv"
    _frame(labels=False).to_csv(path, index=False)
    argv = _argv(path, tmp_path / "runs", "dynamics=physics", "name=phys")
    assert train_main(argv) == 0
    final = json.loads((tmp_path / "runs" / "phys" / "final.json").read_text())
    assert final["test"]["theta_rmse"] is None
    assert np.isfinite(final["test"]["tracking_rmse_norm"])
    # no labels needed: the surrogate D is fitted on units simulated from the model
    # with the given noise, the band on simulated units too
    argv = _argv(path, tmp_path / "runs", "name=sur", "noise=1e-3,1e-3,1e-3")
    assert train_main(argv) == 0
    final = json.loads((tmp_path / "runs" / "sur" / "final.json").read_text())
    assert final["simulated"]["used_for"]["surrogate"] == "simulated training units"
    assert final["simulated"]["noise_source"] == "given"
    assert final["uncertainty"]["file"] == "uncertainty.json"
    assert "simulated" in final["uncertainty"]["fitted_on"]
    result = jaxcal.calibrate(MODEL, path, method="policy", run=tmp_path / "runs/sur")
    assert result.theta_std is not None and np.isfinite(result.theta_std).all()
    # a malformed noise is refused before any folder exists
    argv = _argv(path, tmp_path / "runs", "name=bad", "noise=y1:1e-3")
    assert train_main(argv) == 2
    assert not (tmp_path / "runs" / "bad").exists()


def test_a_filter_policy_streams_with_its_relative_band(tmp_path):
    # the default preset's feature (env.gauss_newton=filter): the band scales the
    # error the policy's filter predicts (jaxcal.calibrators.uncertainty.lag_scale), so
    # the
    # streaming calibrator must carry the filter's covariance from its first sample
    path = tmp_path / "nolabel.csv"
    _frame(labels=False).to_csv(path, index=False)
    argv = _argv(path, tmp_path / "runs", "name=filt", "noise=1e-3,1e-3,1e-3",
                 "env.action=increment", "env.gauss_newton=filter",
                 "env.start=prior")  # fmt: skip
    assert train_main(argv) == 0
    run = tmp_path / "runs" / "filt"
    assert load_band(run).relative
    frame = _frame()
    cal = StreamingCalibrator(run)
    # issue 41 item 5: before its first valid row a stream reports the run's start
    # (the prior, env.start=prior), inside the box; never zeros outside it
    info = cal.step_info(np.array([np.nan, 0.5]), frame.loc[0, ["y1", "y2", "y3"]])
    assert info.reason == "w_nonfinite"
    np.testing.assert_allclose(info.theta, [1.0, 0.5])
    cal.reset()
    steps = [
        cal.step_info(frame.loc[i, ["a", "b"]], frame.loc[i, ["y1", "y2", "y3"]])
        for i in range(5)
    ]  # fmt: skip
    stds = [s.theta_std for s in steps]
    assert all(s.shape == (2,) and np.all(s > 0) and np.isfinite(s).all() for s in stds)
    result = jaxcal.calibrate(MODEL, path, method="policy", run=run, misfit="keep")
    # streamed and batched alike from the first sample (both start at the run's start;
    # float32 and the test session's float64 differ in the 4th digit)
    first = np.flatnonzero(frame.unit == frame.unit[0])[:5]
    assert list(first) == list(range(5))
    streamed = np.stack([s.theta for s in steps])
    np.testing.assert_allclose(streamed, result.theta[first], rtol=2e-3)
    np.testing.assert_allclose(np.stack(stds), result.theta_std[first], rtol=2e-3)
    assert np.isfinite(result.theta_std).all() and (result.theta_std > 0).all()
    # the std follows each sample's predicted error: not one value per time bucket
    assert len(np.unique(result.theta_std[:, 0])) > len(load_band(run).edges)


@pytest.mark.parametrize(
    "bad, message",
    [
        ("model=no_such_model", "unknown model"),
        ("model=/nowhere/m.py:MODEL", "not found"),
        ("data=/nowhere/toy.csv", "not found"),
        ("theta=p,nope", "unknown name"),
        ("test_units=99", "not units"),
    ],
)
def test_bad_model_data_or_theta_exit_2_and_leave_no_run(
    csv, tmp_path, capsys, bad, message
):
    argv = _argv(csv, tmp_path, "name=bad")
    key = bad.partition("=")[0]
    argv = [a for a in argv if not a.startswith(f"{key}=")] + [bad]
    assert train_main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_a_feedback_run_gated_by_an_absolute_run(trained, csv, tmp_path):
    """``calibrate(..., "policy", run=<feedback>, anchor=<absolute>)``: each row is
    one of the two policies' estimates; the anchor needs its band, the run must be
    incremental."""
    runs = tmp_path / "runs"
    inc = ("dynamics=physics", "env.action=increment", "env.cost=log", "name=inc")
    assert train_main(_argv(csv, runs, *inc)) == 0
    opts = dict(method="policy", theta=["p", "q"])
    gated = jaxcal.calibrate(MODEL, csv, run=runs / "inc", anchor=trained, **opts)
    feedback = jaxcal.calibrate(MODEL, csv, run=runs / "inc", **opts).theta
    anchor = jaxcal.calibrate(MODEL, csv, run=trained, **opts).theta
    assert gated.valid.all() and gated.theta_std is not None
    from_feedback = np.isclose(gated.theta, feedback, rtol=1e-6).all(axis=1)
    from_anchor = np.isclose(gated.theta, anchor, rtol=1e-6).all(axis=1)
    assert (from_feedback | from_anchor).all()
    # the real-time API streams the same gate: unit 1's rows, one at a time
    stream = StreamingCalibrator(runs / "inc", anchor=trained)
    frame = _frame()
    rows = np.flatnonzero(frame["unit"].to_numpy() == 1)
    infos = [
        stream.step_info(frame.loc[i, ["a", "b"]], frame.loc[i, ["y1", "y2", "y3"]])
        for i in rows
    ]
    np.testing.assert_allclose(
        np.stack([i.theta for i in infos]), gated.theta[rows], rtol=1e-6
    )
    assert all(isinstance(i.gate_open, bool) and i.valid for i in infos)
    theta, _ = stream.run(
        frame.loc[rows, ["a", "b"]].to_numpy()[None],
        frame.loc[rows, ["y1", "y2", "y3"]].to_numpy()[None],
    )
    np.testing.assert_allclose(theta[0], gated.theta[rows], rtol=1e-6)
    assert evaluate_main([f"run={runs / 'inc'}", f"anchor={trained}", "repeats=2"]) == 0
    report = json.loads((runs / "inc" / "evaluate_gated.json").read_text())
    assert report["anchor"] == str(trained) and np.isfinite(report["theta_rmse"])
    with pytest.raises(ValueError, match="incremental"):
        jaxcal.calibrate(MODEL, csv, run=trained, anchor=trained, **opts)
    bare = tmp_path / "bare"
    shutil.copytree(trained, bare)
    (bare / "uncertainty.json").unlink()
    with pytest.raises(ValueError, match="no uncertainty.json"):
        jaxcal.calibrate(MODEL, csv, run=runs / "inc", anchor=bare, **opts)


def test_default_preset_filter_step_prior_and_chunk_0_train_and_deploy(tmp_path):
    """The default preset on unlabelled data (small budget): the policy observes the
    filter's step and starts as it (gain 1); the untrained policy is scored as chunk
    0, every scoring logs each parameter's simulated error, and the deployed policy
    carries the filter (its noise, its covariance) and the actor's prior."""
    from jaxcal.calibrators.methods.policy.loading import load_run
    from jaxcal.runs.metrics_log import read_metrics

    path = tmp_path / "nolabel.csv"
    _frame(labels=False).to_csv(path, index=False)
    small = (
        "budget.num_chunks=2", "runner.num_envs=4", "runner.num_steps_per_chunk=40",
        "runner.warmup_steps=80", "runner.min_buffer_size=80", "runner.batch_size=32",
        "env.episode_length=10", "simulate.copies=2", "tune.steps=0",
    )  # fmt: skip
    argv = [
        a
        for a in _argv(path, tmp_path / "runs", "name=filt", "noise=1e-3,1e-3,1e-3")
        if a != "preset=smoke"
    ]
    assert train_main([*argv, "preset=default", *small]) == 0
    run_dir = tmp_path / "runs" / "filt"
    records = read_metrics(run_dir / "metrics.jsonl")
    assert [r["step"] for r in records] == [0, 1, 2]
    for r in records:
        assert {"val_sim_theta_rmse_p", "val_sim_theta_rmse_q"} <= set(r)
        assert r["val_sim_theta_rmse"] > 0
    loaded = load_run(run_dir)
    assert loaded.params.gn_filter and loaded.params.gauss_newton
    # the filter's R: the simulated units' noise (here the given noise=), not the
    # provisional 1 % of each output's spread the unlabelled data's problem holds
    stored = json.loads((run_dir / "data.json").read_text())["problem"]
    assert stored["noise_source"].startswith("provisional")
    np.testing.assert_allclose(loaded.params.x_noise, [1e-3] * 3, rtol=1e-6)
    obs_size = 3 + 1 + 2 + 2 + 2 + 2 + 1  # residual, |r|, w, theta, GN, filter, age
    assert loaded.actor.prior == (obs_size - 2 - 1, 1.0)
    result = jaxcal.calibrate(MODEL, path, method="policy", run=run_dir)
    assert result.valid.all() and np.isfinite(result.theta_std).all()
    # issue 41: what training added to its start, in final.json and one plain line
    final = json.loads((run_dir / "final.json").read_text())
    gain = final["training_gain"]
    assert gain["start"] == records[0]["val_sim_theta_rmse"]
    assert gain["kept_start"] == (final["selected_chunk"] == 0)
    assert gain["kept"] == records[final["selected_chunk"]]["val_sim_theta_rmse"]
    line = [ln for ln in format_final(final).splitlines() if "untrained start" in ln]
    assert len(line) == 1
    assert ("did not improve" in line[0]) == gain["kept_start"]
    # budget.num_chunks=0: the untrained policy (the filter's step) is the run's
    start_argv = [*argv, "preset=default", *small[1:], "budget.num_chunks=0"]
    start_argv = [a.replace("name=filt", "name=start") for a in start_argv]
    assert train_main(start_argv) == 0
    start = json.loads((tmp_path / "runs" / "start" / "final.json").read_text())
    assert start["selected_chunk"] == 0 and start["chunks"] == 0
    assert start["training_gain"]["start"] == gain["start"]
    assert np.isfinite(
        jaxcal.calibrate(
            MODEL, path, method="policy", run=tmp_path / "runs" / "start"
        ).theta
    ).all()


@pytest.mark.parametrize("effects", ["simulate.effects=0.5", "tune.effects=0.5"])
def test_tune_keeps_a_tuned_policy_only_where_selection_agrees(tmp_path, effects):
    """``tune.steps``: the untrained policy tuned by gradient through the deployed
    filter; final.json says what it did, and the run deploys the tuned actor
    (``policy_tuned/``) exactly when it lowered the selection's theta error. With
    ``tune.effects`` the score is half effects, and the clean units may not lose."""
    from jaxcal.calibrators.methods.policy.loading import load_run

    path = tmp_path / "nolabel.csv"
    _frame(labels=False).to_csv(path, index=False)
    argv = [
        a
        for a in _argv(path, tmp_path / "runs", "name=tuned", "noise=1e-3,1e-3,1e-3")
        if a != "preset=smoke"
    ]
    small = ("budget.num_chunks=0", "env.episode_length=10", "simulate.copies=2",
             effects, "tune.steps=2", "tune.eval_every=1",
             "tune.batch_units=2", "tune.lr=1e-3")  # fmt: skip
    assert train_main([*argv, "preset=default", *small]) == 0
    run_dir = tmp_path / "runs" / "tuned"
    final = json.loads((run_dir / "final.json").read_text())
    tune = final["tune"]
    assert tune["steps"] in (1, 2)
    assert tune["selection_theta_rmse_after"] <= tune["selection_theta_rmse_before"]
    if effects.startswith("tune."):
        assert tune["score_after"] <= tune["score_before"]
        assert tune["clean_theta_rmse_after"][0] <= tune["clean_theta_rmse_before"][0]
    assert (run_dir / "policy_tuned").is_dir() == tune["improved"]
    assert final["training_gain"].get("tuned", False) == tune["improved"]
    loaded = load_run(run_dir)
    start = load_run(run_dir, step=0)  # chunk 0's checkpoint: the untrained actor
    same = all(
        np.array_equal(a, b)
        for a, b in zip(
            jax.tree.leaves(loaded.params.actor), jax.tree.leaves(start.params.actor),
            strict=True,
        )
    )  # fmt: skip
    assert same != tune["improved"]
    # the default preset's tuning fits the filter's output-bias walks (tune.bias):
    # a tuned policy loads with them, the untrained one has none
    walk = getattr(loaded.params, "filter_bias_var", None)
    assert (walk is not None) == tune["improved"]
    assert getattr(start.params, "filter_bias_var", None) is None
    if tune["improved"]:
        np.testing.assert_allclose(walk, tune["bias_var"])
    result = jaxcal.calibrate(MODEL, path, method="policy", run=run_dir)
    assert result.valid.all() and np.isfinite(result.theta).all()
