"""``python -m jaxcal.evaluate`` and the real-time API ``jaxcal.deploy``.

One smoke run on a synthetic N-CMAPSS file serves every test. The streaming
calibrator, the batch runner, the generic ``Calibrator`` through ``run_fleet`` and the
training environment's own evaluation must all give the same theta.
"""

import json

import jax
import numpy as np
import pytest
from support.synthetic_file import write_synthetic_ncmapss

from jaxcal.calibrators.interface import REASONS, run_fleet
from jaxcal.calibrators.methods.policy.calibrator import stream_start_theta
from jaxcal.cli.evaluate import main, parse_args
from jaxcal.deploy import StreamingCalibrator, load_calibrator, load_run
from jaxcal.envs.tracking import make_env_params, make_tracking_env
from jaxcal.models.turbofan.training import load_calibration_data
from jaxcal.problem import Normalisation
from jaxcal.training.components import make_agent
from jaxcal.training.config import resolve_config
from jaxcal.training.pipeline import run_training
from tests.support.policy_rollout import evaluate_policy


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("deploy")
    path = write_synthetic_ncmapss(root / "synthetic.h5")
    cfg = resolve_config(
        [
            "dataset=ncmapss",
            "preset=smoke",
            f"path={path}",
            "dataset.stride=1",
            f"output.runs_dir={root / 'runs'}",
            "output.progress=false",
        ]
    )
    final = run_training(cfg, log=lambda _: None)
    data = load_calibration_data(str(path))
    return root / "runs" / cfg.run_name, final, data


def test_evaluate_cli_scores_the_test_units_and_writes_json(trained, capsys):
    run_dir, final, _ = trained
    assert main([f"run={run_dir}", "repeats=5"]) == 0
    out = capsys.readouterr().out
    assert "theta RMSE" in out and "single-stream" in out and "samples/s" in out
    report = json.loads((run_dir / "evaluate.json").read_text())
    assert report["units"] == [4, 5]
    assert report["theta_rmse"] == pytest.approx(final["test"]["theta_rmse"])
    dep = report["deployment"]
    assert dep["single_stream_latency_s"]["median_s"] > 0
    assert dep["batched_samples_per_s"] > 0 and dep["batched_units"] == 2
    assert main([f"run={run_dir}", "split=val", "repeats=2"]) == 0
    assert (run_dir / "evaluate_val.json").is_file()


def test_evaluate_rejects_bad_arguments(tmp_path, capsys):
    with pytest.raises(ValueError, match="valid keys: run, split, repeats"):
        parse_args(["run=x", "bogus=1"])
    with pytest.raises(ValueError, match="run=<run folder> is required"):
        parse_args([])
    assert main(["run=x", "split=train"]) == 2
    assert main([f"run={tmp_path}"]) == 2
    assert "config.json" in capsys.readouterr().err


def test_stream_batch_and_calibrator_agree(trained):
    run_dir, _, data = trained
    units = data.test
    cal = StreamingCalibrator(run_dir)
    assert cal.sensors == tuple(data.problem.output_names) and cal.theta_names == (
        "HPT_eff_mod",
    )
    theta, xhat = cal.run(units.w, units.x, units.mask)
    assert theta.shape == units.theta.shape and xhat.shape == units.x.shape
    length = int(units.lengths[1])
    streamed = np.stack(
        [cal.step(w, x) for w, x in zip(units.w[1], units.x[1], strict=True)][:length]
    )
    np.testing.assert_allclose(streamed, theta[1, :length], rtol=1e-5, atol=1e-7)
    cal.reset()
    np.testing.assert_allclose(cal.step(units.w[1, 0], units.x[1, 0]), theta[1, 0])
    out = jax.jit(run_fleet, static_argnums=0)(
        load_calibrator(run_dir), units.w, units.x, units.mask
    )
    np.testing.assert_allclose(out.theta, theta, rtol=1e-5, atol=1e-7)
    lo, hi = load_run(run_dir).params.theta_low, load_run(run_dir).params.theta_high
    assert np.all((theta >= np.asarray(lo) - 1e-7) & (theta <= np.asarray(hi) + 1e-7))
    with pytest.raises(ValueError, match="x must have 1 dimension"):
        cal.step(units.w[0, 0], units.x[0, 0, :3])
    with pytest.raises(ValueError, match="must share"):
        cal.run(units.w, units.x, units.mask[:, :5])


def test_calibrator_reproduces_the_training_environment_rollout(trained):
    run_dir, _, data = trained
    run = load_run(run_dir)
    cfg = run.config
    params = run.params
    units = data.test
    env_params = make_env_params(
        units.w.astype(np.float32),
        units.x.astype(np.float32),
        units.lengths,
        params.theta_low,
        params.theta_high,
        params.dyn_params,
        stats=Normalisation(params.w_mean, params.w_std, params.x_mean, params.x_std),
    )
    from jaxcal.envs.tracking import EnvConfig

    env = make_tracking_env(
        run.dynamics, EnvConfig(units.x.shape[-1], 4, 1, episode_length=10)
    )
    agent = make_agent(cfg.agent, env.observation_size, env.action_size)
    state = agent.init(jax.random.key(0))
    state = state.replace(actor=state.actor.replace(params=params.actor))
    ref = jax.jit(evaluate_policy, static_argnums=(1, 2))(
        jax.random.key(0), env, agent, state, env_params
    )
    theta, xhat = StreamingCalibrator(run).run(units.w, units.x, units.mask)
    mask = np.asarray(ref.mask).copy()
    mask[:, 0] = False  # the first sample differs by design (no x-hat before it)
    np.testing.assert_allclose(theta[mask], np.asarray(ref.theta)[mask], rtol=1e-5)
    np.testing.assert_allclose(xhat[mask], np.asarray(ref.xhat)[mask], rtol=1e-5)


def test_streaming_skips_a_poisoned_sample_and_flags_it(trained):
    """Issue 12: one NaN / Inf / far-out sample must not poison the stream."""
    run_dir, _, data = trained
    units = data.test
    length = int(units.lengths[0])
    w, x = units.w[0, :length].copy(), units.x[0, :length].copy()
    bad = 5
    cal = StreamingCalibrator(run_dir)
    assert cal.check is not None  # the run stored its training range
    clean = [cal.step(w[t], x[t]) for t in range(length) if t != bad]
    for t_bad, value, reason in [
        (bad, np.nan, "x_partial"),  # one output missing: a policy needs them all
        (bad, np.inf, "x_nonfinite"),
        (bad, 1e6, "x_out_of_range"),
    ]:
        cal.reset()
        streamed = []
        for t in range(length):
            x_t = x[t].copy()
            if t == t_bad:
                x_t[0] = value
                info = cal.step_info(w[t], x_t)
                assert (info.valid, info.reason) == (False, reason)
                assert (cal.last_valid, cal.last_reason) == (False, reason)
                np.testing.assert_array_equal(info.theta, streamed[-1])
                continue
            streamed.append(cal.step(w[t], x_t))
            assert cal.last_valid and cal.last_reason == "ok"
        np.testing.assert_array_equal(np.stack(streamed), np.stack(clean))
    # a NaN in w, and before any valid sample: the stream's start (inside the
    # run's box, where its first valid sample steps from), state untouched
    cal.reset()
    w_nan = w[0].copy()
    w_nan[2] = np.nan
    info = cal.step_info(w_nan, x[0])
    assert info.reason == "w_nonfinite"
    params = cal.run_info.params
    start = np.asarray(stream_start_theta(params))
    np.testing.assert_array_equal(info.theta, start)
    assert np.all((params.theta_low <= start) & (start <= params.theta_high))
    np.testing.assert_array_equal(cal.step(w[0], x[0]), clean[0])


def test_batch_run_flags_and_scores_only_valid_samples(trained):
    run_dir, _, data = trained
    units = data.test
    cal = StreamingCalibrator(run_dir)
    x_bad = units.x.copy()
    x_bad[0, 3, 1] = np.nan
    theta, xhat, valid, reason = cal.run(units.w, x_bad, units.mask, return_flags=True)
    assert np.isfinite(theta).all()
    assert not valid[0, 3] and REASONS[reason[0, 3]] == "x_partial"  # one missing
    assert valid[units.mask].sum() == units.mask.sum() - 1
    np.testing.assert_array_equal(theta[0, 3], theta[0, 2])
    theta_ok, _ = cal.run(units.w, units.x, units.mask)
    np.testing.assert_array_equal(theta[1], theta_ok[1])  # other units untouched
    meta = json.loads((run_dir / "data.json").read_text())["problem"]["input_range"]
    assert (
        len(meta["x_low"]) == len(data.problem.output_names)
        and len(meta["w_high"]) == 4
    )


def test_evaluate_report_counts_flagged_samples(trained, capsys):
    run_dir, final, _ = trained
    assert final["test"]["num_flagged"] == 0  # the training job's test scoring
    assert set(final["test"]["flagged"]) >= {"x_nonfinite", "x_out_of_range"}
    assert main([f"run={run_dir}", "repeats=2"]) == 0
    assert "flagged samples" in capsys.readouterr().out
    report = json.loads((run_dir / "evaluate.json").read_text())
    assert report["num_flagged"] == 0 and "x_nonfinite" in report["flagged"]
    assert report["num_scored"] == report["num_samples"]


SYNC_STREAM = """
import sys, numpy as np
from jaxcal.deploy import StreamingCalibrator, synchronous_dispatch
synchronous_dispatch()  # before JAX's first computation
from jaxcal.cache import enable_compilation_cache
from jaxcal.precision import enable_x64
enable_x64(); enable_compilation_cache()
synchronous_dispatch()  # already synchronous: nothing to do
w, x = np.load(sys.argv[2]), np.load(sys.argv[3])
cal = StreamingCalibrator(sys.argv[1])
assert cal.synchronous
print(np.stack([cal.step(w[t], x[t]) for t in range(len(w))]).tobytes().hex())
"""


def test_synchronous_dispatch_runs_the_same_stream_and_refuses_a_started_jax(
    trained, tmp_path
):
    """JAX's dispatch on the calling thread (deployment's lowest cost a row) gives
    the streamed theta of the default dispatch, bit for bit; asked for once JAX has
    started, it says so instead of being ignored."""
    import subprocess
    import sys

    from jaxcal.deploy import synchronous_dispatch

    run_dir, _, data = trained
    units = data.test
    length = min(int(units.lengths[0]), 30)
    w, x = units.w[0, :length], units.x[0, :length]
    cal = StreamingCalibrator(run_dir)
    assert not cal.synchronous  # this process's JAX started with the default
    streamed = np.stack([cal.step(w[t], x[t]) for t in range(length)])
    np.save(tmp_path / "w.npy", w)
    np.save(tmp_path / "x.npy", x)
    out = subprocess.run(
        [sys.executable, "-c", SYNC_STREAM, str(run_dir), str(tmp_path / "w.npy"),
         str(tmp_path / "x.npy")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == streamed.tobytes().hex()
    with pytest.raises(RuntimeError, match="JAX_CPU_ENABLE_ASYNC_DISPATCH=false"):
        synchronous_dispatch()
