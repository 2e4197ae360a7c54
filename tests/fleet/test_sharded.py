"""Sharded fleet calibration: 4 fake CPU devices give the single-device results.

``--xla_force_host_platform_device_count`` only acts before JAX's backend starts, so the
4-device run happens in a fresh interpreter (``fleet_worker.py sharded``), which also
computes the single-device reference (``jax.jit(run_fleet)`` on unsharded arrays) of
the same calibrators; this process compares them.
"""

import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from jaxcal.calibrators.interface import REASON_CODE, SampleCheck
from jaxcal.fleet.sharded import (
    calibrate_sharded,
    make_unit_mesh,
    pad_units,
    padded_size,
    shard_units,
)

WORKER = os.path.join(os.path.dirname(__file__), "fleet_worker.py")


def run_worker(args, env_extra, timeout=240):
    """Run fleet_worker.py; fail with its stderr if it fails or hangs."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", **env_extra}
    try:
        proc = subprocess.run(
            [sys.executable, WORKER, *args],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"worker {args} timed out; stderr:\n{err.stderr}")
    if proc.returncode != 0:
        pytest.fail(f"worker {args} exited {proc.returncode}; stderr:\n{proc.stderr}")
    return proc


@pytest.fixture(scope="module")
def sharded_results(tmp_path_factory):
    out = tmp_path_factory.mktemp("sharded") / "sharded.npz"
    flags = "--xla_force_host_platform_device_count=4"
    run_worker(["sharded", str(out)], {"XLA_FLAGS": flags})
    return dict(np.load(out))


def test_worker_ran_on_four_devices_with_one_block_per_device(sharded_results):
    assert int(sharded_results["num_devices"]) == 4
    assert int(sharded_results["out_devices"]) == 4
    np.testing.assert_array_equal(sharded_results["out_shard_rows"], [2, 2, 2, 2])


@pytest.mark.parametrize("method", ["ukf", "ls"])
@pytest.mark.parametrize("field", ["theta", "xhat", "theta_std"])
def test_sharded_equals_single_device(sharded_results, method, field):
    ref = sharded_results[f"{method}_{field}_ref"]
    got = sharded_results[f"{method}_{field}_sharded"]
    assert got.shape == ref.shape and ref.shape[0] == 6  # 6 units, padded to 8 inside
    assert np.all(np.isfinite(ref))
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-14)


def test_sharded_keys_match_run_fleet_keys(sharded_results):
    ref, got = sharded_results["keys_ref"], sharded_results["keys_sharded"]
    assert np.ptp(ref[:, 0, 0]) > 0  # the keys really differ per unit
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-14)


def test_padded_size():
    assert [padded_size(n, 4) for n in (0, 1, 4, 5, 8)] == [4, 4, 4, 8, 8]
    with pytest.raises(ValueError, match="multiple >= 1"):
        padded_size(3, 0)


def test_pad_units_repeats_last_unit_with_mask_off():
    w = np.arange(3 * 2 * 1, dtype=float).reshape(3, 2, 1)
    x = -w
    mask = np.array([[True, True], [True, False], [True, True]])
    keys = jax.random.split(jax.random.key(0), 3)
    pw, px, pm, pk = pad_units(w, x, mask, 5, keys)
    assert pw.shape == (5, 2, 1) and pm.shape == (5, 2) and pk.shape == (5,)
    np.testing.assert_array_equal(pw[3:], w[[2, 2]])
    np.testing.assert_array_equal(px[3:], x[[2, 2]])
    np.testing.assert_array_equal(pm[:3], mask)
    assert not pm[3:].any()
    with pytest.raises(ValueError, match="1 <= U <= size"):
        pad_units(w, x, mask, 2)


def test_one_device_mesh_matches_run_fleet_and_checks_inputs():
    from fleet_worker import problem, reference, ukf

    w, x, mask, _, measure = problem(num_units=5)  # the reference of other modules
    calibrator = ukf(measure)
    mesh = make_unit_mesh([jax.devices()[0]])
    out = calibrate_sharded(calibrator, w, x, mask, mesh=mesh)
    ref = reference(calibrator, w, x, mask)
    np.testing.assert_allclose(out.theta, ref.theta, rtol=1e-12, atol=1e-14)
    # a poisoned sample: flagged and skipped exactly as run_fleet does (issue 12)
    x_bad = x.copy()
    x_bad[0, 1, 0] = np.inf
    check = SampleCheck(
        w_low=np.full(w.shape[-1], -np.inf), w_high=np.full(w.shape[-1], np.inf)
    )
    out = calibrate_sharded(calibrator, w, x_bad, mask, mesh=mesh, check=check)
    ref = reference(calibrator, w, x_bad, mask)
    np.testing.assert_array_equal(out.reason, ref.reason)
    assert out.reason[0, 1] == REASON_CODE["x_nonfinite"] and not out.valid[0, 1]
    np.testing.assert_allclose(out.theta, ref.theta, rtol=1e-12, atol=1e-14)
    assert np.isfinite(out.theta).all()
    with pytest.raises(ValueError, match="mask must be"):
        calibrate_sharded(calibrator, w, x, mask[:, :3])
    with pytest.raises(ValueError, match="expected w"):
        calibrate_sharded(calibrator, w[0], x[0])


def test_shard_units_rejects_ragged_leaves():
    mesh = make_unit_mesh([jax.devices()[0]])
    with pytest.raises(ValueError, match="same leading size"):
        shard_units(mesh, (np.zeros((2, 3)), np.zeros((3, 3))))
