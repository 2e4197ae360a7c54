"""Subprocess side of the sharded and multi-process fleet tests (not a test module).

The device count of a JAX process is fixed when its backend starts, so tests that need
4 fake CPU devices, or two processes joined by ``jax.distributed``, run this script in
fresh interpreters; the tests compare its ``.npz`` / ``.h5`` output with a
single-device result:

    python fleet_worker.py sharded OUT.npz                 # XLA_FLAGS: 4 devices
    python fleet_worker.py distributed OUT_DIR PORT PROCESS_ID   # 2 processes x 2

The fleet is a tiny analytic problem (``support.analytic``), identical in every
process because it is generated from a fixed key.
"""

from __future__ import annotations

import functools
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

# run as a script in a fresh interpreter: make tests/support importable
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from support.analytic import analytic_dynamics, make_analytic_problem

from jaxcal.calibrators.interface import (
    Calibrator,
    CalStepOutput,
    Measurement,
    run_fleet,
)
from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig, make_least_squares
from jaxcal.calibrators.ukf import UKFConfig, make_ukf

NUM_UNITS, NUM_STEPS, NUM_SENSORS, NUM_PARAMS = 6, 12, 3, 2


@functools.lru_cache(maxsize=4)
def problem(num_units: int = NUM_UNITS):
    """``(w, x, mask, theta, measure)`` of a mildly nonlinear analytic fleet (cached:
    the same ``measure`` object lets tests share compiled programs)."""
    prob = make_analytic_problem(
        jax.random.key(3), num_units=num_units, num_steps=NUM_STEPS,
        sensor_dim=NUM_SENSORS, param_dim=NUM_PARAMS, interaction=0.3,
        noise_std=0.01, min_length=5,
    )  # fmt: skip
    mask = np.arange(NUM_STEPS)[None, :] < np.asarray(prob.lengths)[:, None]

    def measure(w, theta):
        return analytic_dynamics(prob.dyn_params, w, None, theta)

    w, x, theta = (np.asarray(a) for a in (prob.w, prob.x, prob.theta))
    return w, x, mask, theta, measure


@functools.lru_cache(maxsize=4)
def ukf(measure) -> Calibrator:
    meas = Measurement(
        centre=jnp.zeros(NUM_SENSORS), noise_std=jnp.full(NUM_SENSORS, 0.5)
    )
    return make_ukf(measure, UKFConfig(q=0.02), meas, theta0=jnp.full(NUM_PARAMS, 0.4))


def least_squares(measure) -> Calibrator:
    meas = Measurement(centre=jnp.zeros(NUM_SENSORS), noise_std=jnp.ones(NUM_SENSORS))
    cfg = LeastSquaresConfig(window=4, num_iters=2, prior_std=1.0)
    return make_least_squares(measure, cfg, meas, theta0=jnp.full(NUM_PARAMS, 0.4))


def noisy_mean() -> Calibrator:
    """A stochastic toy calibrator: theta starts at a key-dependent draw."""

    def init(key, w0, x0):
        del w0
        return {"theta": jax.random.normal(key, (1,)), "x0": x0}

    def step(state, w_t, x_t):
        theta = 0.9 * state["theta"] + 0.1 * jnp.mean(x_t - state["x0"])
        return {**state, "theta": theta}, CalStepOutput(theta=theta, xhat=x_t + w_t[0])

    return Calibrator(init=init, step=step)


_run_fleet_jit = jax.jit(run_fleet, static_argnums=0)


def reference(calibrator, w, x, mask, keys=None):
    """The single-device path: ``run_fleet`` jitted, on unsharded arrays."""
    out = _run_fleet_jit(calibrator, w, x, mask, keys=keys)
    return jax.tree.map(np.asarray, out)


def run_sharded_check(out_path: str) -> None:
    from jaxcal.fleet import calibrate_sharded, make_unit_mesh, run_sharded, shard_units

    w, x, mask, _, measure = problem()
    results = {"num_devices": np.array(jax.device_count())}
    the_ukf = ukf(measure)
    for name, calibrator in (("ukf", the_ukf), ("ls", least_squares(measure))):
        ref = reference(calibrator, w, x, mask)
        out = calibrate_sharded(calibrator, w, x, mask)
        for field in ("theta", "xhat"):
            results[f"{name}_{field}_ref"] = getattr(ref, field)
            results[f"{name}_{field}_sharded"] = getattr(out, field)
        results[f"{name}_theta_std_ref"] = ref.aux["theta_std"]
        results[f"{name}_theta_std_sharded"] = out.aux["theta_std"]
    keys = jax.random.split(jax.random.key(7), NUM_UNITS)
    toy = noisy_mean()
    results["keys_ref"] = reference(toy, w, x, mask, keys).theta
    results["keys_sharded"] = calibrate_sharded(toy, w, x, mask, keys=keys).theta
    # The outputs of run_sharded stay distributed: one block of units per device (8
    # units: the program calibrate_sharded compiled for 6 units padded to 8).
    mesh = make_unit_mesh()
    w8, x8, m8 = (np.concatenate([a, a[:2]]) for a in (w, x, mask))
    placed = run_sharded(the_ukf, mesh, *shard_units(mesh, (w8, x8, m8)))
    results["out_devices"] = np.array(len(placed.theta.sharding.device_set))
    results["out_shard_rows"] = np.array(
        [s.data.shape[0] for s in placed.theta.addressable_shards]
    )
    np.savez(out_path, **results)


def run_distributed(out_dir: str, port: str, process_id: int) -> None:
    from jaxcal.fleet import (
        FleetResultWriter,
        calibrate_distributed,
        calibrate_stream,
        iter_array_chunks,
        make_unit_mesh,
        process_share,
        units_per_chunk,
    )
    from jaxcal.fleet.distributed import initialize

    initialize(f"127.0.0.1:{port}", 2, process_id, local_device_count=2, timeout_s=60)
    from jaxcal.precision import enable_x64

    enable_x64()
    num_units = 5  # 3 + 2 units: unequal shares, so one process pads more
    w, x, mask, theta, measure = problem(num_units)
    calibrator = ukf(measure)
    mine = process_share(np.arange(num_units))
    out = calibrate_distributed(calibrator, w[mine], x[mine], mask[mine])
    # Streaming over both processes, 3 units per global chunk (2 + 1, then 1 + 1),
    # padded to the 4 units per process of the call above: its program is reused.
    mesh = make_unit_mesh()
    size = 4
    assert size >= units_per_chunk(3, 2, mesh)
    chunks = iter_array_chunks(
        w, x, mask, 3, unit_ids=100 + np.arange(num_units),
        extras={"theta_true": theta}, process_index=jax.process_index(),
        num_processes=jax.process_count(),
    )  # fmt: skip
    if jax.process_index() == 0:
        path = os.path.join(out_dir, "stream.h5")
        names = dict(theta_names=("a", "b"), sensor_names=("s0", "s1", "s2"))
        with FleetResultWriter(path, **names) as writer:
            stats = calibrate_stream(calibrator, chunks, mesh, size=size, writer=writer)
    else:
        stats = calibrate_stream(calibrator, chunks, mesh, size=size)
    np.savez(
        os.path.join(out_dir, f"process{jax.process_index()}.npz"),
        theta=out.theta,
        xhat=out.xhat,
        share=mine,
        num_devices=np.array(jax.device_count()),
        num_local_devices=np.array(jax.local_device_count()),
        num_chunks=np.array(stats["num_chunks"]),
        num_units=np.array(stats["num_units"]),
    )


if __name__ == "__main__":
    from jaxcal.cache import enable_compilation_cache
    from jaxcal.precision import enable_x64

    mode = sys.argv[1]
    enable_compilation_cache()
    if mode == "sharded":
        enable_x64()
        run_sharded_check(sys.argv[2])
    elif mode == "distributed":
        run_distributed(sys.argv[2], sys.argv[3], int(sys.argv[4]))
    else:
        raise SystemExit(f"unknown mode {mode!r}")
