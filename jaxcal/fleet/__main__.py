"""Command line: calibrate every unit of an N-CMAPSS file, sharded, streamed, optionally
on several processes.

Usage::

    python -m jaxcal.fleet data=data/cmapss.h5 method=ukf out=results/fleet/ukf.h5
    python -m jaxcal.fleet data=FILE method=least_squares theta=HPT_eff_mod \\
        sensors=T24,T30,T48,T50 units=7,8 stride=10 chunk_units=4 \\
        least_squares.window=16
    python -m jaxcal.fleet data=FILE method=policy run=runs/<id> out=OUT.h5
    # two processes (same command on each, its own id; or the JAXCAL_* variables):
    python -m jaxcal.fleet --coordinator 10.0.0.1:12355 --num-processes 2 \\
        --process-id 0 data=FILE method=ukf out=OUT.h5

Every ``key=value`` is a field of :class:`FleetConfig` (nested ``ukf.*`` and
``least_squares.*`` fields too), parsed by :func:`jaxcal.cli_args.parse_overrides`.
The cluster flags fall back to ``JAXCAL_COORDINATOR`` / ``JAXCAL_NUM_PROCESSES`` /
``JAXCAL_PROCESS_ID``; ``--local-devices K`` splits each process's CPU into ``K``
devices.
Process 0 writes ``out`` (atomically) and prints a JSON summary; a bad argument prints
the error and exits with code 2. See ``docs/fleet.md``.

Samples with NaN / Inf, or outside the model's valid inputs (the engine's envelope for
``ukf`` / ``least_squares``, the run's training range for ``policy``), are skipped and
flagged: the file's ``valid`` / ``reason`` columns, ``flagged`` counts per reason in the
summary; ``theta_rmse`` is over valid rows only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from typing import Literal

import h5py
import numpy as np

from jaxcal.calibrators.least_squares import LeastSquaresConfig
from jaxcal.calibrators.ukf import UKFConfig
from jaxcal.cli_args import parse_command_line
from jaxcal.physics.constants import MEASURED_SENSOR_NAMES
from jaxcal.settings import config_to_dict, parse_overrides

DEFAULT_THETA_SCALE = 0.01  # of a health modifier (see FleetConfig.theta_scale)
USAGE = (
    "usage: python -m jaxcal.fleet data=FILE.h5 out=OUT.h5 "
    "[method=ukf|least_squares|policy] [run=RUN_DIR] [field=value ...] "
    "[--coordinator HOST:PORT --num-processes N --process-id I] [--local-devices K]"
)


@dataclasses.dataclass(frozen=True)
class FleetConfig:
    """What ``python -m jaxcal.fleet`` runs (every field settable as ``key=value``)."""

    data: str = ""  # input file in the N-CMAPSS HDF5 layout (required)
    out: str = ""  # output results file (required; written atomically by process 0)
    split: Literal["dev", "test"] = "test"  # which split of the file
    method: Literal["ukf", "least_squares", "policy"] = "ukf"
    run: str = ""  # method=policy: the training run directory (runs/<id>)
    engine: Literal["cmapss", "agtf30"] = "cmapss"  # model F of ukf / least_squares
    theta: tuple[str, ...] = ("HPT_eff_mod",)  # declared parameters (HEALTH_NAMES)
    sensors: tuple[str, ...] = ()  # () = the file's observed_sensors, else X_s
    units: tuple[int, ...] = ()  # () = every unit of the split
    stride: int = 1  # keep file rows 0, stride, 2 stride, ...
    chunk_units: int = 0  # units per global chunk; 0 = one per device
    max_len: int = 0  # padded length T; 0 = the longest selected unit
    theta0: tuple[float, ...] = ()  # prior mean / start per parameter; () = 0
    # the filters work in theta / theta_scale; () = 0.01 each: health modifiers are
    # O(1 %), so ukf.q, ukf.prior_std are in percent (raw units would put the UKF's
    # sigma points at theta = +-1, far outside the engine's envelope)
    theta_scale: tuple[float, ...] = ()
    unroll: int = 1  # lax.scan unroll factor
    ukf: UKFConfig = UKFConfig()  # method=ukf settings (q = r = 0.01 as the paper)
    least_squares: LeastSquaresConfig = LeastSquaresConfig()  # method=least_squares


def parse_args(argv: list[str]) -> tuple[FleetConfig, dict]:
    """The resolved config and cluster settings of a command line.

    Args:
        argv: ``key=value`` tokens and ``--flag value`` cluster options.

    Returns:
        ``(config, cluster)`` with ``cluster`` keys ``coordinator``,
        ``num_processes``, ``process_id``, ``local_device_count``.

    Raises:
        ValueError: naming the bad key or flag and the expected form.
    """
    from jaxcal.fleet.distributed import process_settings

    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--coordinator", default=None)
    parser.add_argument("--num-processes", type=int, default=None)
    parser.add_argument("--process-id", type=int, default=None)
    parser.add_argument("--local-devices", type=int, default=None)
    try:
        flags, rest = parser.parse_known_args(argv)
    except SystemExit:
        raise ValueError("bad cluster flag (expected --name value)") from None
    unknown = [t for t in rest if t.startswith("--")]
    if unknown:
        raise ValueError(
            f"unknown flag(s) {unknown}; flags are --coordinator, --num-processes, "
            "--process-id, --local-devices"
        )
    cfg = parse_overrides(rest, FleetConfig())
    if not cfg.data or not cfg.out:
        raise ValueError("data=<file.h5> and out=<results.h5> are required")
    if cfg.method == "policy" and not cfg.run:
        raise ValueError("method=policy needs run=<runs/...> (training run dir)")
    if cfg.stride < 1 or cfg.chunk_units < 0 or cfg.max_len < 0 or cfg.unroll < 1:
        raise ValueError(
            "need stride >= 1, chunk_units >= 0, max_len >= 0 and unroll >= 1"
        )
    for name in ("theta0", "theta_scale"):
        if getattr(cfg, name) and len(getattr(cfg, name)) != len(cfg.theta):
            raise ValueError(
                f"{name} needs one value per theta name ({len(cfg.theta)} values)"
            )
    coordinator, num_processes, process_id = process_settings(
        flags.coordinator, flags.num_processes, flags.process_id
    )
    cluster = {
        "coordinator": coordinator,
        "num_processes": num_processes,
        "process_id": process_id,
        "local_device_count": flags.local_devices,
    }
    return cfg, cluster


def file_sensors(path: str) -> tuple[str, ...]:
    """The file's ``observed_sensors`` attribute, else its measured sensors ``X_s``."""
    with h5py.File(path, "r") as f:
        observed = f.attrs.get("observed_sensors")
        names = [n.decode().strip() for n in f["X_s_var"][()]] if "X_s_var" in f else []
    if isinstance(observed, bytes):
        observed = observed.decode()
    if isinstance(observed, str) and observed:
        return tuple(json.loads(observed))
    return tuple(n for n in names if n in MEASURED_SENSOR_NAMES)


def build_calibrator(cfg: FleetConfig, sensors: tuple[str, ...], norm):
    """The :class:`~jaxcal.calibrators.interface.Calibrator` of ``cfg.method``."""
    import jax.numpy as jnp

    from jaxcal.calibrators.interface import measure_declared

    if cfg.method == "policy":
        from jaxcal.deploy import load_calibrator

        return load_calibrator(cfg.run)
    from jaxcal.calibrators.least_squares import make_least_squares
    from jaxcal.calibrators.ukf import make_ukf
    from jaxcal.physics import load_engine

    engine = load_engine(cfg.engine)
    measure = measure_declared(
        lambda w, th: engine.evaluate(w, th)[0],
        jnp.zeros(len(engine.health_names)),  # undeclared parameters: healthy
        cfg.theta,
        sensors,
    )
    theta0 = jnp.asarray(cfg.theta0 or (0.0,) * len(cfg.theta))
    scale = jnp.asarray(cfg.theta_scale or (DEFAULT_THETA_SCALE,) * len(cfg.theta))
    if cfg.method == "ukf":
        return make_ukf(measure, cfg.ukf, norm, theta0=theta0, theta_scale=scale)
    return make_least_squares(
        measure, cfg.least_squares, norm, theta0=theta0, theta_scale=scale
    )


def build_check(cfg: FleetConfig):
    """The valid input box of ``cfg.method``: the engine's envelope, or the policy
    run's training range (``None`` for a run that predates it: finiteness only)."""
    from jaxcal.calibrators.interface import SampleCheck

    if cfg.method == "policy":
        from jaxcal.deploy import load_run, run_check

        return run_check(load_run(cfg.run))
    from jaxcal.physics.engine import ENVELOPES

    return SampleCheck.from_envelope(ENVELOPES[cfg.engine])


def theta_rmse(path: str, block_rows: int = 1 << 20) -> list[float] | None:
    """Per-parameter RMSE of ``theta`` against ``theta_true`` in a results file,
    over its valid (not flagged) rows."""
    with h5py.File(path, "r") as f:
        if "theta_true" not in f:
            return None
        total, sq = 0, 0.0
        for a in range(0, f["theta"].shape[0], block_rows):
            err = f["theta"][a : a + block_rows] - f["theta_true"][a : a + block_rows]
            if "valid" in f:  # flagged rows repeat an older theta: not scored
                err = err[f["valid"][a : a + block_rows]]
            total += err.shape[0]
            sq = sq + np.square(err).sum(axis=0)
    return np.sqrt(sq / max(total, 1)).tolist()


def run(cfg: FleetConfig) -> dict:
    """Calibrate the selected units of ``cfg.data``; process 0 writes ``cfg.out``."""
    import jax

    from jaxcal.fleet.ncmapss_source import (
        iter_ncmapss_chunks,
        sensor_norm,
        unit_lengths,
    )
    from jaxcal.fleet.results import FleetResultWriter
    from jaxcal.fleet.sharded import make_unit_mesh
    from jaxcal.fleet.streaming import calibrate_stream, units_per_chunk

    sensors = cfg.sensors or file_sensors(cfg.data)
    units = cfg.units or None
    unit_ids, lengths = unit_lengths(cfg.data, cfg.split, units, stride=cfg.stride)
    max_len = cfg.max_len or int(lengths.max())
    norm, norm_source = sensor_norm(
        cfg.data, cfg.split, sensors, units, stride=cfg.stride
    )
    calibrator = build_calibrator(cfg, sensors, norm)
    check = build_check(cfg)
    mesh = make_unit_mesh()
    num_processes, process_index = jax.process_count(), jax.process_index()
    chunk_units = cfg.chunk_units or mesh.size
    size = units_per_chunk(chunk_units, num_processes, mesh)
    chunks = iter_ncmapss_chunks(
        cfg.data, cfg.split, unit_ids, max_len=max_len, chunk_units=chunk_units,
        sensors=sensors, theta_names=cfg.theta, stride=cfg.stride,
        process_index=process_index, num_processes=num_processes,
    )  # fmt: skip
    attrs = {
        "config": config_to_dict(cfg),
        "method": cfg.method,
        "source": f"{cfg.data}[{cfg.split}]",
        "norm_source": norm_source,
        "num_processes": num_processes,
        "num_devices": mesh.size,
    }
    if process_index == 0:
        with FleetResultWriter(
            cfg.out, theta_names=cfg.theta, sensor_names=sensors, attrs=attrs
        ) as writer:
            stats = calibrate_stream(
                calibrator, chunks, mesh, size=size, writer=writer,
                unroll=cfg.unroll, check=check,
            )  # fmt: skip
        rmse = theta_rmse(cfg.out)
    else:
        stats = calibrate_stream(
            calibrator, chunks, mesh, size=size, unroll=cfg.unroll, check=check
        )
        rmse = None
    return {
        **stats,
        "out": cfg.out,
        "max_len": max_len,
        "units_per_chunk_per_process": size,
        "num_devices": mesh.size,
        "num_processes": num_processes,
        "theta_rmse": rmse,
    }


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parsed, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if code is not None:
        return code
    cfg, cluster = parsed
    from jaxcal.fleet.distributed import initialize
    from jaxcal.precision import enable_compilation_cache, enable_x64

    # Before any JAX computation: the cluster, then float64 (the engine's solver).
    try:
        initialize(**cluster)
    except RuntimeError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    enable_x64()
    enable_compilation_cache()
    try:
        summary = run(cfg)
    except (ValueError, FileNotFoundError, KeyError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    import jax

    if jax.process_index() == 0:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
