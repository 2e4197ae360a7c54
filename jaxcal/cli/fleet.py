"""Command line: calibrate every unit of a fleet, sharded, streamed, optionally on
several processes.

Usage::

    python -m jaxcal.fleet data=data/cmapss.h5 method=ukf out=results/fleet/ukf.h5
    python -m jaxcal.fleet model=heat_exchanger data=fleet.csv method=ukf \\
        noise=T_hot_out:0.05,T_cold_out:0.05,dp_hot:0.2,duty:1 out=OUT.h5
    python -m jaxcal.fleet model=my_model.py:model data=fleet.parquet method=ls \\
        theta=leak noise=0.1 window=16 out=OUT.h5
    python -m jaxcal.fleet data=FILE.h5 method=ls theta=HPT_eff_mod \\
        outputs=T24,T30,T48,T50 units=7,8 stride=10 chunk_units=4 window=16 out=OUT.h5
    python -m jaxcal.fleet data=FILE method=policy run=runs/<id> out=OUT.h5
    # two processes (same command on each, its own id; or the JAXCAL_* variables):
    python -m jaxcal.fleet --coordinator 10.0.0.1:12355 --num-processes 2 \\
        --process-id 0 data=FILE method=ukf out=OUT.h5

``model=`` is any :func:`jaxcal.models.load` spec (a registered name such as
``cmapss``, ``heat_exchanger``, ``thermal``; ``path/to/file.py:attr``; an
``extended_model.json``; its ``.py`` base, and a policy run's model copy, run only
with ``trust_code=true``, ``docs/trust.md``), default ``cmapss`` (``engine=`` is its
old name). ``data=``
is an N-CMAPSS ``.h5`` file (the turbofan's layout, streamed: never read whole) or any
table the front door reads (``.csv``, ``.parquet``, C-MAPSS ``.txt``; held in memory),
its columns named as the model's (:mod:`jaxcal.fleet.sources`). The method is built
from the front door's method table (:mod:`jaxcal.fleet.method`): ``method=`` any
registered method (``ukf``, ``ls``, ``e2e``, ``policy``, ...; ``least_squares`` is
the old name of ``ls``; a method that learns from the whole data set on tables only),
and every key that is not a field of :class:`FleetConfig` is an option of the method
(``q=``, ``prior_std=``, ``window=``, ``num_iters=``, ``state_std=``, ``anchor=``,
...; the old ``ukf.q=`` / ``least_squares.window=`` forms still work): a misspelt one
prints the valid ones and exits with code 2. ``noise=`` is the measurement noise
std, ``name:std,...`` per output or one number for all; without it the turbofan
keeps its default (1 % of each output's spread) and other models are refused.
Fields are parsed by :func:`jaxcal.settings.parse_overrides`.
The cluster flags fall back to ``JAXCAL_COORDINATOR`` / ``JAXCAL_NUM_PROCESSES`` /
``JAXCAL_PROCESS_ID``; ``--local-devices K`` splits each process's CPU into ``K``
devices.
Process 0 writes ``out`` (atomically; columns named by the problem's parameters and
outputs) and prints a JSON summary; a bad argument prints the error and exits with
code 2. See ``docs/fleet.md``.

An extended model whose added parameter lists its carriers (``"units"`` in
``extended_model.json``) is calibrated as ``jaxcal.calibrate`` does it: the UKF, least
squares and E2E track the parameter in the carriers only and hold it at its nominal
value (0) with std 0 in every other unit (:mod:`jaxcal.fleet.per_unit`); the summary
and the file's attributes say which units held what (``unit_runs``, ``notes``).

Samples with NaN / Inf, or outside the method's valid inputs (the model's condition
range for ``ukf`` / ``ls``, the run's training range for ``policy``, the data's for
``e2e``), are skipped and flagged: the file's ``valid`` / ``reason`` columns,
``flagged`` counts per reason in the summary; ``theta_rmse`` is over valid rows only.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import sys
from typing import Any

import h5py
import jax
import numpy as np

from jaxcal.cache import enable_compilation_cache
from jaxcal.calibrators import methods
from jaxcal.calibrators.front.carriers import nominal_values
from jaxcal.cli.args import CLUSTER_USAGE, parse_command_line, split_cluster_args
from jaxcal.fleet.distributed import initialize
from jaxcal.fleet.method import (
    OPTION_PREFIXES,
    build_problem,
    canonical,
    make_method,
    method_options,
    parse_noise,
    require_noise,
)
from jaxcal.fleet.results import FleetResultWriter
from jaxcal.fleet.sharded import make_unit_mesh
from jaxcal.fleet.streaming import units_per_chunk
from jaxcal.precision import enable_x64
from jaxcal.settings import check_output_path, config_to_dict, parse_overrides

USAGE = (
    "usage: python -m jaxcal.fleet data=FILE out=OUT.h5 [model=SPEC] "
    "[method=ukf|ls|e2e|policy] [run=RUN_DIR] [noise=NAME:STD,...|STD] "
    f"[field=value ...] [option=value ...] {CLUSTER_USAGE}"
)


@dataclasses.dataclass(frozen=True)
class FleetConfig:
    """What ``python -m jaxcal.fleet`` runs (every field but ``options`` settable as
    ``key=value``; any other key is an option of the method, kept in ``options``)."""

    data: str = ""  # N-CMAPSS .h5 (streamed) or a table: .csv, .parquet, .txt
    out: str = ""  # output results file (required; written atomically by process 0)
    model: str = ""  # jaxcal.models.load spec; "" = engine=
    engine: str = "cmapss"  # old name of model=
    split: str = ""  # N-CMAPSS: dev | test ("" = test); a table's split label ("" all)
    method: str = "ukf"  # a registered method (jaxcal.calibrators.methods)
    run: str = ""  # method=policy: the training run directory (runs/<id>)
    theta: tuple[str, ...] = ()  # () = a policy's, the turbofan's HPT_eff_mod, or all
    outputs: tuple[str, ...] = ()  # () = a policy's, the file's observed_sensors
    # else X_s (N-CMAPSS), or every model output of the table
    sensors: tuple[str, ...] = ()  # old name of outputs=
    noise: str = ""  # measurement noise std: name:std,... or one number
    units: tuple[int, ...] = ()  # () = every unit (of the split)
    stride: int = 1  # keep file rows 0, stride, 2 stride, ...
    chunk_units: int = 0  # units per global chunk; 0 = one per device
    max_len: int = 0  # padded length T; 0 = the longest selected unit
    theta0: tuple[float, ...] = ()  # prior mean / start per parameter; () = nominal
    unroll: int = 1  # lax.scan unroll factor
    seed: int = 0  # method=e2e: training seed
    trust_code: bool = False  # run a run's model copy / a JSON spec's .py base
    options: tuple[tuple[str, Any], ...] = ()  # the method's (name, value) options


FLEET_KEYS = tuple(
    f.name for f in dataclasses.fields(FleetConfig) if f.name != "options"
)


def _split_tokens(tokens: list[str]) -> tuple[list[str], list[tuple]]:
    """Fleet ``key=value`` tokens, and the method's ``(prefix, name, text)``."""
    fleet, options = [], []
    for token in tokens:
        key, sep, text = token.partition("=")
        key = key.strip()
        head, dot, name = key.partition(".")
        if key == "theta_scale":
            raise ValueError(
                "theta_scale= is gone: the parameters are scaled by half their box "
                "(the model's bounds), as in jaxcal.calibrate; q and prior_std are "
                "in those units"
            )
        if sep and dot and head in OPTION_PREFIXES:
            options.append((head, name, text))
        elif sep and key and not dot and key not in FLEET_KEYS:
            options.append((None, key, text))
        else:
            fleet.append(token)
    return fleet, options


def method_config(cfg: FleetConfig, run=None):
    """The method table's config of ``cfg`` (a policy's ``run``: loaded or a path)."""
    options = dict(cfg.options)
    if methods.get(cfg.method).needs_run:
        options["run"] = run if run is not None else cfg.run
    return methods.config(cfg.method, options)


def parse_args(argv: list[str]) -> tuple[FleetConfig, dict]:
    """The resolved config and cluster settings of a command line.

    Args:
        argv: ``key=value`` tokens and ``--flag value`` cluster options.

    Returns:
        ``(config, cluster)`` with ``cluster`` keys ``coordinator``,
        ``num_processes``, ``process_id``, ``local_device_count``.

    Raises:
        ValueError: naming the bad key, option or flag and the expected form.
    """
    # the turbofan's and the method's code load after the arguments are checked
    from jaxcal.models.turbofan.fleet import is_ncmapss

    rest, flags = split_cluster_args(argv)
    fleet_tokens, option_tokens = _split_tokens(rest)
    cfg = parse_overrides(fleet_tokens, FleetConfig())
    method = canonical(cfg.method)
    methods.get(method)  # an unknown method: the registered ones listed
    options = method_options(method, option_tokens, FLEET_KEYS)
    cfg = dataclasses.replace(cfg, method=method, options=options)
    if not cfg.data or not cfg.out:
        raise ValueError("data=<file> and out=<results.h5> are required")
    check_output_path(cfg.out, "out")  # refused now, not after the calibration
    needs = methods.get(method)
    if needs.needs_run and not cfg.run:
        raise ValueError(f"method={method} needs run=<runs/...> (training run dir)")
    if needs.needs_all_rows and is_ncmapss(cfg.data):
        raise ValueError(
            f"method={method} learns from the whole data set: give the data as a "
            "table (.csv, .parquet), or use jaxcal.calibrate"
        )
    method_config(cfg)  # a bad option value fails here, before any work
    parse_noise(cfg.noise)
    if cfg.stride < 1 or cfg.chunk_units < 0 or cfg.max_len < 0 or cfg.unroll < 1:
        raise ValueError(
            "need stride >= 1, chunk_units >= 0, max_len >= 0 and unroll >= 1"
        )
    if cfg.outputs and cfg.sensors:
        raise ValueError("outputs= and its old name sensors= are both given")
    if cfg.theta and cfg.theta0 and len(cfg.theta0) != len(cfg.theta):
        raise ValueError(
            f"theta0 needs one value per theta name ({len(cfg.theta)} values)"
        )
    return cfg, flags.resolve()


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
    """Calibrate the selected units of ``cfg.data``; process 0 writes ``cfg.out``.

    A parameter that acts in some units only (an extended model's carriers) is
    calibrated in those units and held at its nominal value with std 0 in the
    others, as by ``jaxcal.calibrate`` (:mod:`jaxcal.fleet.per_unit`)."""
    # the turbofan's, the sources' and the runs' code load when the fleet runs
    from jaxcal.fleet.per_unit import plan_runs, stream_runs
    from jaxcal.fleet.sources import open_source
    from jaxcal.models import load
    from jaxcal.models.turbofan.fleet import is_ncmapss, open_ncmapss
    from jaxcal.models.turbofan.model import FLEET_NOISE, is_turbofan

    model = load(cfg.model or cfg.engine, trust_code=cfg.trust_code)
    noise = parse_noise(cfg.noise)
    default_noise = FLEET_NOISE if is_turbofan(model) else None
    require_noise(model, cfg.method, noise, default_noise)
    theta, outputs, loaded = _names(cfg, model)
    if cfg.theta0 and len(cfg.theta0) != len(theta):
        raise ValueError(f"theta0 needs one value per theta name {list(theta)}")
    source = (open_ncmapss if is_ncmapss(cfg.data) else open_source)(
        cfg.data, model, outputs=outputs, split=cfg.split, units=cfg.units,
        stride=cfg.stride, max_len=cfg.max_len,
    )  # fmt: skip
    runs, note = plan_runs(model, theta, source.unit_ids, cfg.method, dict(cfg.options))
    start = dict(zip(theta, cfg.theta0, strict=False))  # theta0 per name ({}: nominal)

    def problem_of(names):
        return build_problem(
            model, source, theta=names, method=cfg.method, noise=noise,
            default_noise=default_noise,
            theta0=[start[k] for k in names] if start else (),
        )  # fmt: skip

    problem = problem_of(theta)  # the file's: every parameter of theta
    fleets = {}  # the parameters a group calibrates -> its method (module doc)
    for names in dict.fromkeys(r.theta for r in runs):
        own = problem if names == problem.theta_names else problem_of(names)
        fleets[names] = make_method(own, method_config(cfg, loaded), source, cfg.seed)
    mesh = make_unit_mesh()
    num_processes, process_index = jax.process_count(), jax.process_index()
    chunk_units = cfg.chunk_units or mesh.size
    size = units_per_chunk(chunk_units, num_processes, mesh)
    groups = [
        {"units": r.unit_ids.tolist(), "theta": list(r.theta)} for r in runs
    ] if note else None  # fmt: skip
    attrs = {
        "config": config_to_dict(cfg),
        "method": cfg.method,
        "model": model.name,
        "source": source.description,
        "norm_source": source.norm_source,
        "noise_std": problem.noise_std.tolist(),
        "noise_source": problem.noise_source,
        "num_processes": num_processes,
        "num_devices": mesh.size,
        **({"unit_runs": groups, "notes": [note]} if note else {}),
    }
    stream = functools.partial(
        stream_runs, runs, fleets, source, mesh, theta_names=problem.theta_names,
        nominal=nominal_values(model, problem.theta_names), chunk_units=chunk_units,
        size=size, unroll=cfg.unroll,
    )  # fmt: skip
    if process_index == 0:
        with FleetResultWriter(
            cfg.out, theta_names=problem.theta_names,
            sensor_names=problem.output_names, attrs=attrs,
        ) as writer:  # fmt: skip
            stats = stream(writer=writer)
        rmse = theta_rmse(cfg.out)
    else:
        stats = stream(writer=None)
        rmse = None
    return {
        **stats,
        "out": cfg.out,
        "model": model.name,
        "method": cfg.method,
        "theta_names": list(problem.theta_names),
        "noise_source": problem.noise_source,
        "max_len": source.max_len,
        "units_per_chunk_per_process": size,
        "num_devices": mesh.size,
        "num_processes": num_processes,
        "theta_rmse": rmse,
        **({"unit_runs": groups, "notes": [note]} if note else {}),
    }


def _names(cfg: FleetConfig, model):
    """``(theta, outputs, loaded)``: the calibrated parameters and the outputs used,
    a policy's run loaded (``None`` for another method): a trained policy fixes its
    names, the defaults; otherwise the model's default parameters."""
    # the turbofan loads only for a model that asks for it
    from jaxcal.models.turbofan.model import FLEET_THETA, is_turbofan

    theta, outputs, loaded = cfg.theta, cfg.outputs or cfg.sensors, None
    if methods.get(cfg.method).needs_run:  # a trained run fixes its names: its own
        # the deploy layer loads only for a trained run
        from jaxcal.deploy import load_run

        loaded = load_run(cfg.run, trust_code=cfg.trust_code)
        theta = theta or loaded.problem.theta_names
        outputs = outputs or loaded.problem.output_names
    default = FLEET_THETA if is_turbofan(model) else tuple(model.parameter_names)
    return tuple(theta) or default, outputs, loaded


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parsed, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if code is not None:
        return code
    cfg, cluster = parsed
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
    if jax.process_index() == 0:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
