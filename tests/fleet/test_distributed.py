"""Two JAX processes on localhost (``jax.distributed``, gloo CPU collectives), 2 fake
CPU devices each, calibrate one analytic fleet; the gathered results equal the
single-process ``run_fleet`` results."""

import os
import sys

import numpy as np
import pytest
from fleet_worker import problem, reference, ukf
from support.processes import free_port, run_processes

from jaxcal.fleet.distributed import (
    initialize,
    process_settings,
    process_share,
)
from jaxcal.fleet.results import read_results

WORKER = os.path.join(os.path.dirname(__file__), "fleet_worker.py")
TIMEOUT_S = 240


@pytest.fixture(scope="module")
def two_process_run(tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("distributed")
    port = str(free_port())
    commands = [
        [sys.executable, WORKER, "distributed", str(out_dir), port, str(i)]
        for i in range(2)
    ]
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    _, errors = run_processes(commands, env, TIMEOUT_S)
    if errors:
        pytest.fail("\n\n".join(errors))
    return out_dir


def test_two_processes_each_see_four_global_devices(two_process_run):
    for i in range(2):
        got = np.load(two_process_run / f"process{i}.npz")
        assert int(got["num_devices"]) == 4 and int(got["num_local_devices"]) == 2
    shares = [np.load(two_process_run / f"process{i}.npz")["share"] for i in range(2)]
    assert [s.tolist() for s in shares] == [[0, 1, 2], [3, 4]]


def test_gathered_theta_equals_single_process(two_process_run):
    w, x, mask, _, measure = problem(num_units=5)
    ref = reference(ukf(measure), w, x, mask)
    for i in range(2):  # every process holds the whole fleet's results
        got = np.load(two_process_run / f"process{i}.npz")
        np.testing.assert_allclose(got["theta"], ref.theta, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(got["xhat"], ref.xhat, rtol=1e-12, atol=1e-14)


def test_streamed_file_from_process_zero_equals_single_process(two_process_run):
    w, x, mask, theta, measure = problem(num_units=5)
    ref = reference(ukf(measure), w, x, mask)
    arrays, _ = read_results(two_process_run / "stream.h5")
    np.testing.assert_allclose(arrays["theta"], ref.theta[mask], rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(arrays["theta_true"], theta[mask])
    np.testing.assert_array_equal(arrays["unit_id"], 100 + np.arange(5))
    stats = np.load(two_process_run / "process1.npz")
    assert int(stats["num_chunks"]) == 2 and int(stats["num_units"]) == 5
    assert sorted(os.listdir(two_process_run)) == [
        "process0.npz",
        "process1.npz",
        "stream.h5",
    ]


def test_process_share_blocks():
    blocks = [process_share(np.arange(7), p, 3).tolist() for p in range(3)]
    assert blocks == [[0, 1, 2], [3, 4], [5, 6]]
    with pytest.raises(ValueError, match="process_index"):
        process_share(np.arange(3), 3, 3)


@pytest.mark.parametrize(
    "args, match",
    [
        ((None, 2, 0), "coordinator must be 'host:port'"),
        (("localhost", 2, 0), "coordinator must be 'host:port'"),
        (("127.0.0.1:1234", 2, 2), "process_id must lie in"),
        (("127.0.0.1:1234", 0, 0), "num_processes must be >= 1"),
    ],
)
def test_bad_cluster_settings_raise(args, match):
    with pytest.raises(ValueError, match=match):
        initialize(*args)


def test_settings_from_environment():
    env = {
        "JAXCAL_COORDINATOR": "10.0.0.1:9000",
        "JAXCAL_NUM_PROCESSES": "4",
        "JAXCAL_PROCESS_ID": "3",
    }
    assert process_settings(environ=env) == ("10.0.0.1:9000", 4, 3)
    assert process_settings(environ={}) == (None, 1, 0)
    with pytest.raises(ValueError, match="must be integers"):
        process_settings(environ={"JAXCAL_NUM_PROCESSES": "two"})


def test_initialize_after_jax_started_is_a_clear_error():
    import jax

    jax.devices()  # the backend of this test process is up
    with pytest.raises(RuntimeError, match="before any JAX computation"):
        initialize(None, 1, 0, local_device_count=2)
