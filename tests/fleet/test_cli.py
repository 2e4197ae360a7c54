"""``python -m jaxcal.fleet``: argument handling, and (slow) an engine run."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from jaxcal.fleet.__main__ import FleetConfig, main, parse_args
from jaxcal.fleet.results import read_results


def test_overrides_and_cluster_flags():
    argv = [
        "data=in.h5", "out=o.h5", "method=least_squares",
        "theta=HPT_eff_mod,LPT_eff_mod", "units=3,4", "least_squares.window=8",
        "--coordinator", "127.0.0.1:4000",
        "--num-processes", "2", "--process-id", "1", "--local-devices", "2",
    ]  # fmt: skip
    cfg, cluster = parse_args(argv)
    assert isinstance(cfg, FleetConfig)
    assert cfg.method == "least_squares" and cfg.units == (3, 4)
    assert cfg.theta == ("HPT_eff_mod", "LPT_eff_mod")
    assert cfg.least_squares.window == 8
    assert cluster == {
        "coordinator": "127.0.0.1:4000",
        "num_processes": 2,
        "process_id": 1,
        "local_device_count": 2,
    }


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["out=o.h5"], "data=<file.h5> and out=<results.h5> are required"),
        (["data=a.h5", "out=o.h5", "method=kalman"], "expected one of ukf"),
        (["data=a.h5", "out=o.h5", "method=policy"], "needs run="),
        (["data=a.h5", "out=o.h5", "bogus=1"], "unknown key 'bogus'"),
        (["data=a.h5", "out=o.h5", "ukf.q=-1"], "UKFConfig.q must be > 0"),
        (["data=a.h5", "out=o.h5", "theta0=0,0"], "one value per theta name"),
        (["data=a.h5", "out=o.h5", "--num-processes", "2"], "coordinator must be"),
        (["data=a.h5", "out=o.h5", "--workers", "2"], "unknown flag"),
    ],
)
def test_bad_arguments_exit_2_with_the_reason(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_policy_without_a_trained_run_is_a_clear_error(tmp_path):
    from jaxcal.fleet.__main__ import build_calibrator

    cfg = FleetConfig(data="a.h5", out="o.h5", method="policy", run=str(tmp_path))
    with pytest.raises(FileNotFoundError, match="config.json"):
        build_calibrator(cfg, ("T24",), None)


@pytest.mark.slow
def test_engine_ukf_run_recovers_theta(tmp_path):
    """A tiny engine fleet: 3 units with constant HPT efficiency loss, 2 devices."""
    import jax.numpy as jnp

    from jaxcal.data.ncmapss_io import write_ncmapss
    from jaxcal.data.record import Record
    from jaxcal.physics import load_engine
    from jaxcal.physics.atmosphere import isa_total_temperature
    from jaxcal.physics.constants import HEALTH_NAMES, SENSOR_NAMES

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
    np.testing.assert_array_equal(arrays["unit_length"], lengths)
    assert not arrays["valid"][5] and arrays["valid"].sum() == n - 1
    # The last estimate of each unit is close to its (constant) true loss.
    np.testing.assert_allclose(arrays["unit_theta_last"][:, 0], losses, atol=1e-3)
