"""``python -m jaxcal.fleet``: argument handling, any model on a table or an N-CMAPSS
file (in process, one process), and (slow) an engine run."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from jaxcal.cli.fleet import FleetConfig, main, parse_args
from jaxcal.fleet.results import read_results

HX_UNITS, HX_ROWS = (4, 9, 2), 50  # unit ids (not in order) and rows per unit
HX_NOISE = {"T_hot_out": 0.05, "T_cold_out": 0.05, "dp_hot": 0.05, "duty": 0.5}


def test_overrides_and_cluster_flags():
    argv = [
        "data=in.h5", "out=o.h5", "method=least_squares",
        "theta=HPT_eff_mod,LPT_eff_mod", "units=3,4", "least_squares.window=8",
        "num_iters=2", "--coordinator", "127.0.0.1:4000",
        "--num-processes", "2", "--process-id", "1", "--local-devices", "2",
    ]  # fmt: skip
    cfg, cluster = parse_args(argv)
    assert isinstance(cfg, FleetConfig)
    assert cfg.method == "ls" and cfg.units == (3, 4)  # least_squares: old name
    assert cfg.theta == ("HPT_eff_mod", "LPT_eff_mod")
    assert cfg.options == (("num_iters", 2), ("window", 8))  # typed, flat
    assert cluster == {
        "coordinator": "127.0.0.1:4000",
        "num_processes": 2,
        "process_id": 1,
        "local_device_count": 2,
    }
    cfg, _ = parse_args(["data=a.csv", "out=o.h5", "ukf.q=0.001", "prior_std=2"])
    assert cfg.method == "ukf" and cfg.options == (("prior_std", 2.0), ("q", 0.001))
    cfg, _ = parse_args(["data=a.csv", "out=o", "method=ls", "state_std=z:0.1,y:2"])
    assert cfg.options == (("state_std", {"z": 0.1, "y": 2.0}),)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["out=o.h5"], "data=<file> and out=<results.h5> are required"),
        (["data=a.h5", "out=o.h5", "method=kalman"], "must be one of ('ukf'"),
        (["data=a.h5", "out=o.h5", "method=policy"], "needs run="),
        (["data=a.h5", "out=o.h5", "bogus=1"], "unknown key 'bogus'"),
        (["data=a.h5", "out=o.h5", "ukf.q=-1"], "q=-1.0 is not a finite number > 0"),
        (["data=a.h5", "out=o.h5", "least_squares.window=4"], "method='ls', but"),
        (["data=a.h5", "out=o.h5", "ukf.r=0.1"], "the measurement noise is noise="),
        (["data=a.h5", "out=o.h5", "theta_scale=0.01"], "theta_scale= is gone"),
        (["data=a.h5", "out=o.h5", "noise=T24"], "expected name:std"),
        (["data=a.h5", "out=o.h5", "method=e2e"], "method=e2e learns from the whole"),
        (["data=a.h5", "out=o.h5", "theta=HPT_eff_mod", "theta0=0,0"], "one value"),
        (["data=a.h5", "out=o.h5", "--num-processes", "2"], "coordinator must be"),
        (["data=a.h5", "out=o.h5", "--workers", "2"], "unknown flag"),
    ],
)
def test_bad_arguments_exit_2_with_the_reason(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_a_misspelt_option_lists_the_valid_ones(capsys):
    argv = ["model=heat_exchanger", "data=x.csv", "out=o.h5", "method=ls", "wndow=8"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "unknown key 'wndow' (did you mean 'window'?)" in err
    assert "method='ls' takes the options" in err
    for option in ("num_iters", "prior_std", "window", "state_std"):
        assert option in err


@pytest.fixture(scope="module")
def hx_csv(tmp_path_factory):
    """3 units x 50 rows of the heat exchanger at its nominal parameters, small
    noise, units and rows shuffled in the file."""
    from jaxcal.models import load

    model = load("heat_exchanger")
    rng = np.random.default_rng(0)
    low, high = (np.asarray(b) for b in model.condition_range)
    n = len(HX_UNITS) * HX_ROWS
    w = rng.uniform(low, high, (n, len(low)))
    theta = np.broadcast_to(model.nominal, (n, len(model.nominal)))
    evaluate = jax.vmap(lambda w_t, th: model.evaluate(w_t, th)[0])
    x = np.asarray(evaluate(jnp.asarray(w), jnp.asarray(theta)))
    x = x + rng.normal(size=x.shape) * [HX_NOISE[s] for s in model.output_names]
    frame = pd.DataFrame(w, columns=model.condition_names)
    frame[list(model.output_names)] = x
    frame["unit"] = np.repeat(HX_UNITS, HX_ROWS)
    frame["time"] = np.tile(np.arange(HX_ROWS), len(HX_UNITS))
    frame[list(model.parameter_names)] = theta  # true values: theta_true, RMSE
    frame = frame.sample(frac=1.0, random_state=1)  # the reader orders by unit, time
    path = tmp_path_factory.mktemp("hx") / "hx.csv"
    frame.to_csv(path, index=False)
    return path, frame.reset_index(drop=True), model


@pytest.mark.parametrize("method", ["ukf", "ekf"])
def test_heat_exchanger_csv_one_row_per_input_row(hx_csv, tmp_path, capsys, method):
    path, frame, model = hx_csv
    out = tmp_path / "hx.h5"
    noise = ",".join(f"{k}:{v}" for k, v in HX_NOISE.items())
    argv = [
        "model=heat_exchanger", f"data={path}", f"method={method}", f"noise={noise}",
        f"out={out}", "chunk_units=2",
    ]  # fmt: skip
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["num_rows"] == len(frame) and summary["num_chunks"] == 2
    assert summary["num_flagged"] == 0 and summary["noise_source"] == "given"
    arrays, attrs = read_results(out)
    assert attrs["theta_names"] == list(model.parameter_names)
    assert attrs["sensor_names"] == list(model.output_names)
    assert attrs["model"] == "heat_exchanger" and attrs["method"] == method
    assert attrs["noise_std"] == list(HX_NOISE.values())
    # one row per input row: units ascending, time order, each row's source row
    assert arrays["theta"].shape == (len(frame), 3) and arrays["valid"].all()
    np.testing.assert_array_equal(np.sort(arrays["row"]), np.arange(len(frame)))
    np.testing.assert_array_equal(arrays["unit"], frame["unit"][arrays["row"]])
    np.testing.assert_array_equal(arrays["time"], frame["time"][arrays["row"]])
    np.testing.assert_array_equal(arrays["unit_id"], sorted(HX_UNITS))
    # estimates near nominal (fouling 0, dp_coeff 10, heat_loss 0.02)
    near = np.array([0.01, 0.1, 0.005])  # ~1 % of each parameter's box or less
    assert np.all(np.abs(arrays["unit_theta_last"] - model.nominal) < near)
    width = model.bounds[1] - model.bounds[0]  # every row, the first ones too
    assert np.all(np.asarray(summary["theta_rmse"]) < 0.05 * width)


def test_table_source_selects_units_rows_and_pads(hx_csv):
    from jaxcal.fleet.sources import open_source

    path, frame, model = hx_csv
    source = open_source(str(path), model, units=(9, 2), stride=2, max_len=40)
    assert source.complete and source.x_stats is None and source.max_len == 40
    np.testing.assert_array_equal(source.unit_ids, [2, 9])
    chunks = list(source.chunks(model.parameter_names, 1))
    assert [c.unit_ids.tolist() for c in chunks] == [[2], [9]]
    for chunk in chunks:
        rows = chunk.extras["row"][chunk.mask]
        assert chunk.x.shape == (1, 40, 4) and rows.size == chunk.mask.sum()
        np.testing.assert_array_equal(frame["unit"][rows], chunk.unit_ids[0])
        np.testing.assert_array_equal(rows % 2, 0)  # file rows 0, 2, 4, ...
        np.testing.assert_array_equal(np.diff(frame["time"][rows]) > 0, True)
        np.testing.assert_array_equal(chunk.x[chunk.mask], frame.loc[rows, list(
            model.output_names)])  # fmt: skip
        np.testing.assert_array_equal(chunk.extras["theta_true"][0, -1], model.nominal)
    assert sum(int(c.mask.sum()) for c in chunks) == (frame["unit"] != 4)[::2].sum()
    with pytest.raises(ValueError, match="max_len=10 is shorter"):
        open_source(str(path), model, max_len=10)


def test_another_model_without_noise_is_refused(hx_csv, tmp_path, capsys):
    path, _, _ = hx_csv
    argv = ["model=heat_exchanger", f"data={path}", f"out={tmp_path / 'o.h5'}"]
    assert main(argv) == 2
    assert "model 'heat_exchanger': pass noise=" in capsys.readouterr().err
    argv[0] = "model=cmapss"  # the turbofan's conditions are not in the table
    assert main([*argv, "noise=0.1"]) == 2
    assert "columns do not match model 'cmapss'" in capsys.readouterr().err


def test_policy_without_a_trained_run_is_a_clear_error(hx_csv, tmp_path, capsys):
    path, _, _ = hx_csv
    argv = [
        "model=heat_exchanger", f"data={path}", f"out={tmp_path / 'o.h5'}",
        "method=policy", f"run={tmp_path}",
    ]  # fmt: skip
    assert main(argv) == 2
    assert "config.json" in capsys.readouterr().err


TOY_TURBOFAN = """
import jax.numpy as jnp
from jaxcal.model import Model


def toy(w, theta):
    alt, tra = w[0] / 1e4, w[2] / 100
    hpt, lpt = theta
    return jnp.stack([
        500 + 30 * w[1] + 80 * tra + 0.1 * w[3] - 900 * hpt,
        1200 + 50 * alt + 300 * tra - 400 * hpt - 700 * lpt,
        900 + 200 * tra + 40 * alt - 1500 * lpt + 300 * hpt * tra,
    ])


MODEL = Model.from_function(
    toy, conditions=("alt", "Mach", "TRA", "T2"),
    parameters={"HPT_eff_mod": (0.0, -0.1, 0.03), "LPT_eff_mod": (0.0, -0.1, 0.03)},
    outputs=("T24", "T30", "T50"), name="toy_turbofan",
    condition_range=([-1000, 0, 15, 400], [45000, 0.9, 105, 600]),
)
"""


def test_ncmapss_file_streamed_with_a_model_from_a_file(tmp_path, capsys):
    """The N-CMAPSS path with any model of its names: a cheap analytic one."""
    from jaxcal.models.turbofan.data.ncmapss_io import write_ncmapss
    from jaxcal.models.turbofan.data.record import Record
    from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES, SENSOR_NAMES

    (tmp_path / "toy.py").write_text(TOY_TURBOFAN)
    from jaxcal.models import load

    model = load(f"{tmp_path / 'toy.py'}:MODEL")
    rng = np.random.default_rng(0)
    lengths, losses = [30, 24, 36], [-0.004, -0.01, -0.016]
    n = sum(lengths)
    w = rng.uniform([1e4, 0.3, 60, 480], [3e4, 0.7, 90, 520], (n, 4))
    theta = np.zeros((n, len(HEALTH_NAMES)))
    theta[:, HEALTH_NAMES.index("HPT_eff_mod")] = np.repeat(losses, lengths)
    x = rng.normal(size=(n, len(SENSOR_NAMES))) + 500
    cols = [SENSOR_NAMES.index(s) for s in model.output_names]
    declared = theta[:, [HEALTH_NAMES.index(p) for p in model.parameter_names]]
    x[:, cols] = np.asarray(jax.vmap(model.evaluate)(w, declared)[0])
    w[7, 0] = 60000.0  # outside the model's condition range: skipped and flagged
    rec = Record(
        w=w, x=x, x_names=SENSOR_NAMES, theta=theta, unit=np.repeat([1, 2, 3], lengths),
        cycle=np.ones(n, int), flight_class=np.ones(n), hs=np.ones(n),
        rul=np.zeros(n, int),
    )  # fmt: skip
    data = tmp_path / "toy.h5"
    write_ncmapss(data, rec, rec)
    out = tmp_path / "toy_out.h5"
    argv = [
        f"model={tmp_path / 'toy.py'}:MODEL", f"data={data}", f"out={out}",
        "outputs=T24,T30,T50", "noise=0.01", "ukf.q=0.001", "split=dev",
    ]  # fmt: skip
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["num_rows"] == n and summary["flagged"]["w_out_of_range"] == 1
    arrays, attrs = read_results(out)
    assert attrs["norm_source"] == "data pass" and attrs["source"] == f"{data}[dev]"
    assert attrs["theta_names"] == ["HPT_eff_mod", "LPT_eff_mod"]
    assert not arrays["valid"][7] and arrays["valid"].sum() == n - 1
    np.testing.assert_array_equal(arrays["unit_length"], lengths)
    np.testing.assert_array_equal(arrays["theta_true"], declared)
    last = arrays["unit_theta_last"]
    np.testing.assert_allclose(last[:, 0], losses, atol=1e-3)
    np.testing.assert_allclose(last[:, 1], 0.0, atol=1e-3)
    # the heat exchanger's conditions are not the file's: a clear error
    argv[0] = "model=heat_exchanger"
    assert main(argv) == 2
    assert "an N-CMAPSS file holds the turbofan's conditions" in (
        capsys.readouterr().err
    )


# make test-long: the fleet CLI on the turbofan (the engine compiles); the same CLI in
# make test on a model from a file: test_ncmapss_file_streamed_with_a_model_from_a_file
@pytest.mark.slow
def test_engine_ukf_run_recovers_theta(tmp_path):
    """A tiny engine fleet: 3 units with constant HPT efficiency loss, 2 devices."""
    from jaxcal.models.turbofan.data.ncmapss_io import write_ncmapss
    from jaxcal.models.turbofan.data.record import Record
    from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
    from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES, SENSOR_NAMES
    from jaxcal.models.turbofan.physics.engine import load_engine

    engine = load_engine("cmapss")
    rng = np.random.default_rng(0)
    lengths, losses = [12, 9, 15], [-0.004, -0.01, -0.016]
    n = sum(lengths)
    w = np.column_stack(
        [
            rng.uniform(20000, 30000, n),
            rng.uniform(0.6, 0.75, n),
            rng.uniform(70, 85, n),
            np.zeros(n),
        ]
    )
    w[:, 3] = np.asarray(isa_total_temperature(jnp.asarray(w[:, 0]), w[:, 1]))
    theta = np.zeros((n, len(HEALTH_NAMES)))
    theta[:, HEALTH_NAMES.index("HPT_eff_mod")] = np.repeat(losses, lengths)
    x, info = engine.evaluate(jnp.asarray(w), jnp.asarray(theta))
    assert bool(np.all(info.converged))
    w[5, 0] = 60000.0  # above the envelope (issue 12): skipped and flagged
    unit = np.repeat([1, 2, 3], lengths)
    rec = Record(
        w=w, x=np.asarray(x), x_names=SENSOR_NAMES, theta=theta, unit=unit,
        cycle=np.ones(n, int), flight_class=np.ones(n), hs=np.ones(n),
        rul=np.zeros(n, int),
    )  # fmt: skip
    data = tmp_path / "engine.h5"
    write_ncmapss(data, rec, rec)
    out = tmp_path / "ukf.h5"
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    proc = subprocess.run(
        [
            sys.executable, "-m", "jaxcal.fleet", f"data={data}", f"out={out}",
            "split=test", "method=ukf", "sensors=T24,T30,T48,T50,P30,Nf,Nc,Wf",
            "ukf.q=0.001",
        ],
        env=env, capture_output=True, text=True, timeout=1200,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["num_units"] == 3 and summary["num_devices"] == 2
    assert summary["num_flagged"] == 1 and summary["flagged"]["w_out_of_range"] == 1
    arrays, attrs = read_results(out)
    assert attrs["norm_source"] == "data pass" and attrs["method"] == "ukf"
    assert attrs["model"] == "cmapss" and "turbofan's default" in attrs["noise_source"]
    np.testing.assert_array_equal(arrays["unit_length"], lengths)
    assert not arrays["valid"][5] and arrays["valid"].sum() == n - 1
    # The last estimate of each unit is close to its (constant) true loss.
    np.testing.assert_allclose(arrays["unit_theta_last"][:, 0], losses, atol=1e-3)
