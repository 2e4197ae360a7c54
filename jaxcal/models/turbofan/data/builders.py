"""Build the paper's data sets with the engine model and write them as N-CMAPSS files.

Pipeline of :func:`build_dataset` (all host loops run over units, scenarios and chunks,
never over samples or time steps):

1. A *plan* (:func:`make_fleet_plan`, :func:`make_scenario_plan`) samples the static
   parts: degradation trajectories or the factorial fault design, cruise flights, the
   dev/test split. Its ``blocks`` function yields (w, theta) rows block by block from
   jitted, vmapped generators (flights vmapped over cycles, scenarios over the design).
2. A healthy *reference* pass (theta = 0 on each unit's first flight, or on the cruise
   flights) gives per-sensor mean / std / power, which scale the noise variants so that
   they do not depend on the chunking, and Newton warm starts for the scenarios (each
   scenario flies a reference flight, so the healthy solution at the same time step is
   a start a few iterations from the faulty one).
3. Rows are re-cut into fixed ``chunk_size`` chunks and solved by one jitted engine
   call each (:mod:`jaxcal.models.turbofan.data.chunked_engine`: padding, warm-started
   re-solves of non-converged samples, a ``ValueError`` naming unit, cycle and w for any
   left; nothing is ever written as NaN).
4. Noise variants use one PRNG key per (unit, cycle, sample), so the file does not
   depend on chunk or block sizes. Chunks are appended to
   :class:`~jaxcal.models.turbofan.data.ncmapss_io.NCMAPSSWriter` (temp file + rename):
   memory stays at a few chunks whatever the data-set size.

Keys: ``key(seed)`` splits into a plan key and a noise key; units, cycles and flights
draw from ``fold_in`` of their ids, so a unit's data does not change when other units
are added or when blocks are regrouped.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterator
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.models.turbofan.data.chunked_engine import (
    NUM_UNKNOWNS,
    RowBlock,
    concat_rows,
    iter_chunks,
    jit_evaluate_engine,
    jit_perturb_outputs,
    reference_stats,
    solve_all,
    solve_rows,
)
from jaxcal.models.turbofan.data.cruise_band import CruiseBand, sample_cruise_band
from jaxcal.models.turbofan.data.dataset_configs import DatasetConfig
from jaxcal.models.turbofan.data.degradation import (
    DegradationConfig,
    factorial_fault_scenarios,
    sample_rows,
    sample_unit_degradation,
    slice_cycles,
)
from jaxcal.models.turbofan.data.flights import FlightConfig, sample_flight
from jaxcal.models.turbofan.data.ncmapss_io import SPLITS, NCMAPSSWriter
from jaxcal.models.turbofan.data.record import Record
from jaxcal.models.turbofan.physics.constants import SENSOR_NAMES
from jaxcal.models.turbofan.physics.engine import load_engine
from jaxcal.precision import require_x64
from jaxcal.settings import config_to_dict


class DatasetPlan(NamedTuple):
    """What a builder needs to know before solving (see the module docstring)."""

    reference: RowBlock  # healthy reference rows (noise scale, warm starts)
    units: dict[str, np.ndarray]  # split -> unit ids in file order
    num_blocks: int  # generation blocks over both splits (progress)
    blocks: Callable[[str, np.ndarray], Iterator[RowBlock]]  # (split, z_ref) -> rows
    attrs: dict  # extra root attributes of the file


class BuildSummary(NamedTuple):
    """Result of :func:`build_dataset`."""

    path: str
    rows: dict[str, int]  # split -> rows written
    units: dict[str, list[int]]  # split -> unit ids
    num_chunks: int  # engine calls on data chunks (without retries)
    num_retried: int  # samples that needed a warm-started re-solve


# ------------------------------------------------------------- pure generators


def fleet_block_rows(key, deg, start, unit, flight_class, *, flight_cfg, num_cycles):
    """Rows of ``num_cycles`` consecutive flights of one run-to-failure unit.

    The flight of cycle ``c`` uses key ``fold_in(key, c)``, so a flight does not
    depend on how cycles are grouped into blocks.

    Args:
        key: the unit's flight key.
        deg: the unit's
            :class:`~jaxcal.models.turbofan.data.degradation.UnitDegradation` (C_max).
        start: first cycle of the block, 0-based (may be traced).
        unit: [] unit id.
        flight_class: [] the unit's flight class.
        flight_cfg: static :class:`FlightConfig`.
        num_cycles: static block length B.

    Returns:
        (SampleRows of B*T rows, step [B*T] sample index within each flight).
    """
    block = slice_cycles(deg, start, num_cycles)
    keys = jax.vmap(lambda c: jax.random.fold_in(key, c))(block.cycle)
    flights = jax.vmap(lambda k: sample_flight(k, flight_class, flight_cfg))(keys)
    rows = sample_rows(flights.w, flights.mask, block, unit, flight_class)
    step = jnp.tile(jnp.arange(flight_cfg.num_steps), num_cycles)
    return rows, step


def scenario_block_rows(w_flights, z_ref, theta, flight):
    """Rows of B fault scenarios, each flying one reference flight.

    Args:
        w_flights: [F, T, 4] the cruise flights.
        z_ref: [F, T, 9] healthy Newton solutions on them (warm starts).
        theta: [B, 10] scenario health modifiers.
        flight: [B] int flight index 1..F of each scenario.

    Returns:
        (w [B*T, 4], theta [B*T, 10], z0 [B*T, 9]), scenario-major.
    """
    num_steps = w_flights.shape[1]
    theta = jnp.broadcast_to(theta[:, None, :], (theta.shape[0], num_steps, 10))
    flat = lambda a: a.reshape(-1, a.shape[-1])  # noqa: E731
    return flat(w_flights[flight - 1]), flat(theta), flat(z_ref[flight - 1])


# Entry-point jits of the generators, created once per process (shared compiled code).
_jit_fleet_block = jax.jit(
    fleet_block_rows, static_argnames=("flight_cfg", "num_cycles")
)
_jit_scenario_block = jax.jit(scenario_block_rows)


@functools.partial(jax.jit, static_argnames=("num_cycles_max", "deg_cfg"))
def _sample_degradations(keys, classes, *, num_cycles_max, deg_cfg):
    sample = lambda k, c: sample_unit_degradation(k, num_cycles_max, deg_cfg, c)  # noqa: E731
    return jax.vmap(sample)(keys, classes)


@functools.partial(jax.jit, static_argnames=("num_steps", "band"))
def _sample_cruise_flights(keys, *, num_steps, band):
    return jax.vmap(lambda k: sample_cruise_band(k, num_steps, band))(keys)


# ------------------------------------------------------------------------- plans


def _scale_range(bounds, scale):
    return tuple(tuple(max(1, round(v * scale)) for v in pair) for pair in bounds)


def degradation_config(cfg: DatasetConfig) -> DegradationConfig:
    """The run-to-failure settings of a fleet, with ``life_scale`` applied."""
    base = DegradationConfig(degrading=cfg.degrading)
    if cfg.life_scale == 1.0:
        return base
    return dataclasses.replace(
        base,
        onset_cycles=_scale_range(base.onset_cycles, cfg.life_scale),
        eol_cycles=_scale_range(base.eol_cycles, cfg.life_scale),
        min_abnormal_cycles=max(1, round(base.min_abnormal_cycles * cfg.life_scale)),
    )


def _rows_from_samples(rows, step, keep, theta=None) -> RowBlock:
    rows = jax.tree.map(np.asarray, rows)
    keep = np.asarray(keep)
    theta = rows.theta if theta is None else theta
    n = int(keep.sum())
    return RowBlock(
        w=rows.w[keep], theta=theta[keep], z0=np.zeros((n, NUM_UNKNOWNS)),
        unit=rows.unit[keep].astype(np.int64), cycle=rows.cycle[keep].astype(np.int64),
        fc=rows.fc[keep].astype(np.int64), hs=rows.hs[keep].astype(np.int64),
        rul=rows.rul[keep].astype(np.int64), step=np.asarray(step)[keep],
    )  # fmt: skip


def make_fleet_plan(cfg: DatasetConfig, key) -> DatasetPlan:
    """Plan of a run-to-failure fleet (Dataset #1): degradation, flights per block."""
    key_deg, key_flight = jax.random.split(key)
    deg_cfg = degradation_config(cfg)
    block = cfg.cycles_per_block
    c_max = math.ceil(deg_cfg.max_eol_cycle / block) * block
    units = np.arange(1, cfg.num_units + 1)
    classes = np.asarray(cfg.unit_classes)
    fold = jax.vmap(jax.random.fold_in, in_axes=(None, 0))
    deg = _sample_degradations(
        fold(key_deg, units), classes, num_cycles_max=c_max, deg_cfg=deg_cfg
    )
    flight_keys = fold(key_flight, units)
    flight_cfg = FlightConfig(dt_s=cfg.dt_s)
    eol = np.asarray(deg.eol_cycle)

    deg_units = [jax.tree.map(lambda a, i=i: a[i], deg) for i in range(units.size)]

    def unit_block(u, start):
        return _jit_fleet_block(
            flight_keys[u - 1], deg_units[u - 1], start, u, int(classes[u - 1]),
            flight_cfg=flight_cfg, num_cycles=block,
        )  # fmt: skip

    ref = []
    for u in units:  # healthy first flight of every unit
        rows, step = unit_block(int(u), 0)
        keep = np.asarray(rows.mask) & (np.asarray(rows.cycle) == 1)
        ref.append(_rows_from_samples(rows, step, keep, np.zeros(rows.theta.shape)))

    split_units = {"dev": np.asarray(sorted(cfg.dev_units)),
                   "test": np.asarray(cfg.test_units, dtype=np.int64)}  # fmt: skip

    def blocks(split, z_ref):
        del z_ref  # every flight differs: solves start cold
        for u in split_units[split]:
            for start in range(0, int(eol[u - 1]), block):
                rows, step = unit_block(int(u), start)
                yield _rows_from_samples(rows, step, rows.mask)

    num_blocks = int(sum(math.ceil(e / block) for e in eol))
    attrs = {"unit_eol_cycle": eol, "unit_onset_cycle": np.asarray(deg.onset_cycle)}
    return DatasetPlan(concat_rows(ref), split_units, num_blocks, blocks, attrs)


def scenario_design(cfg: DatasetConfig, key) -> dict[str, np.ndarray]:
    """Scenario ids, theta, flight index and split of the factorial design.

    Returns:
        ``{"unit": [M] ids (design row + 1), "theta": [M, 10], "flight": [M] 1..F,
        "test": [M] bool}`` for the M selected scenarios, ascending by id.
    """
    key_subset, key_flight, key_split = jax.random.split(key, 3)
    theta = np.asarray(factorial_fault_scenarios(
        {name: cfg.fault_levels for name in cfg.degrading}
    ))  # fmt: skip
    full = theta.shape[0]
    ids = np.arange(full)
    if cfg.num_scenarios is not None and cfg.num_scenarios < full:
        pick = jax.random.choice(key_subset, full, (cfg.num_scenarios,), replace=False)
        ids = np.sort(np.asarray(pick))
    # balanced flight assignment over the full design: a scenario keeps its flight
    # whatever subset is drawn
    rank = np.argsort(np.asarray(jax.random.permutation(key_flight, full)))
    flight = rank[ids] % cfg.num_flights + 1
    num_test = min(int(round(cfg.test_fraction * ids.size)), ids.size - 1)
    order = np.asarray(jax.random.permutation(key_split, ids.size))
    test = np.zeros(ids.size, bool)
    test[order[:num_test]] = True
    return {"unit": ids + 1, "theta": theta[ids], "flight": flight, "test": test}


def make_scenario_plan(cfg: DatasetConfig, key) -> DatasetPlan:
    """Plan of the fault-scenario set (Dataset #2): cruise flights x fault design."""
    key_design, key_flight = jax.random.split(key)
    design = scenario_design(cfg, key_design)
    flight_keys = jax.vmap(jax.random.fold_in, in_axes=(None, 0))(
        key_flight, jnp.arange(1, cfg.num_flights + 1)
    )
    flights = _sample_cruise_flights(
        flight_keys, num_steps=cfg.flight_steps, band=CruiseBand(dt_s=cfg.dt_s)
    )
    w_flights = np.asarray(flights.w)  # [F, T, 4]
    num_f, num_t = w_flights.shape[:2]
    grid = lambda a: np.repeat(a, num_t)  # noqa: E731
    steps = np.tile(np.arange(num_t), num_f)
    reference = RowBlock(
        w=w_flights.reshape(-1, 4), theta=np.zeros((num_f * num_t, 10)),
        z0=np.zeros((num_f * num_t, NUM_UNKNOWNS)), unit=grid(np.arange(1, num_f + 1)),
        cycle=np.ones(num_f * num_t, np.int64), fc=grid(np.arange(1, num_f + 1)),
        hs=np.ones(num_f * num_t, np.int64), rul=np.zeros(num_f * num_t, np.int64),
        step=steps,
    )  # fmt: skip
    index = {s: np.flatnonzero(design["test"] == (s == "test")) for s in SPLITS}
    size = cfg.scenarios_per_block

    def blocks(split, z_ref):
        z_ref = z_ref.reshape(num_f, num_t, NUM_UNKNOWNS)
        for first in range(0, index[split].size, size):
            rows = index[split][first : first + size]
            pad = np.resize(rows, size)  # fixed block shape: one compile
            w, theta, z0 = _jit_scenario_block(
                w_flights, z_ref, design["theta"][pad], design["flight"][pad]
            )
            n = rows.size * num_t
            per_row = lambda v, rows=rows: np.repeat(v[rows], num_t)  # noqa: E731
            yield RowBlock(
                w=np.asarray(w)[:n], theta=np.asarray(theta)[:n],
                z0=np.asarray(z0)[:n], unit=per_row(design["unit"]),
                cycle=np.ones(n, np.int64), fc=per_row(design["flight"]),
                hs=np.ones(n, np.int64), rul=np.zeros(n, np.int64),
                step=np.tile(np.arange(num_t), rows.size),
            )  # fmt: skip

    units = {s: design["unit"][index[s]] for s in SPLITS}
    num_blocks = sum(math.ceil(index[s].size / size) for s in SPLITS)
    attrs = {"scenario_theta_names": list(cfg.degrading)}
    return DatasetPlan(reference, units, num_blocks, blocks, attrs)


def _to_record(cfg: DatasetConfig, rows: RowBlock, x: np.ndarray) -> Record:
    return Record(
        w=rows.w, x=x, x_names=SENSOR_NAMES, theta=rows.theta, unit=rows.unit,
        cycle=rows.cycle, flight_class=rows.fc, hs=rows.hs, rul=rows.rul,
        sample_rate_hz=cfg.sample_rate_hz, source=f"jaxcal.generate:{cfg.name}",
    )  # fmt: skip


def build_dataset(
    cfg: DatasetConfig,
    path,
    *,
    evaluate=None,
    on_block: Callable[[int, int, int], None] | None = None,
) -> BuildSummary:
    """Generate the data set ``cfg`` and write it to ``path`` (N-CMAPSS layout).

    Args:
        cfg: the data set (see :mod:`jaxcal.models.turbofan.data.dataset_configs`).
        path: output ``.h5``; its directory must exist. Written atomically.
        evaluate: ``(engine, w, theta, z0) -> (x, converged, z)`` on one chunk;
            default :data:`jit_evaluate_engine` (shared compiled code).
        on_block: called as ``on_block(blocks_done, num_blocks, rows_written)`` after
            each generation block (progress bars).

    Returns:
        :class:`BuildSummary`.

    Raises:
        ValueError: float64 is off, or engine samples do not converge.
    """
    require_x64("build_dataset needs float64")
    evaluate = jit_evaluate_engine if evaluate is None else evaluate
    engine = load_engine(cfg.engine)
    solve = functools.partial(
        solve_rows, evaluate, engine,
        chunk_size=cfg.chunk_size, max_retries=cfg.max_retries,
    )  # fmt: skip
    key_plan, key_noise = jax.random.split(jax.random.key(cfg.seed))
    make_plan = make_fleet_plan if cfg.kind == "fleet" else make_scenario_plan
    plan = make_plan(cfg, key_plan)
    x_ref, z_ref, num_retried = solve_all(
        evaluate, engine, plan.reference,
        chunk_size=cfg.chunk_size, max_retries=cfg.max_retries,
    )  # fmt: skip
    stats = reference_stats(x_ref)
    snr = math.inf if cfg.sensor_snr_db is None else cfg.sensor_snr_db
    noise_settings = (cfg.output_bias, cfg.output_noise_sigma, snr)
    attrs = {
        "config": config_to_dict(cfg), "dataset": cfg.name, "engine": cfg.engine,
        "observed_sensors": list(cfg.observed_sensors),
        "reference_x_names": list(SENSOR_NAMES),
        **{f"reference_x_{k}": v for k, v in stats.items()}, **plan.attrs,
    }  # fmt: skip
    rows = dict.fromkeys(SPLITS, 0)
    blocks_done, num_chunks = 0, 0
    with NCMAPSSWriter(path, attrs=attrs) as writer:
        for split in SPLITS:
            for chunk, block_end in iter_chunks(
                plan.blocks(split, z_ref), cfg.chunk_size
            ):
                if block_end:
                    blocks_done += 1
                    if on_block is not None:
                        on_block(blocks_done, plan.num_blocks, sum(rows.values()))
                    continue
                x, _, retried = solve(chunk, where=f"{split} chunk {num_chunks}")
                if cfg.has_noise:
                    x = np.asarray(jit_perturb_outputs(
                        key_noise, x, chunk.unit, chunk.cycle, chunk.step, stats,
                        *noise_settings,
                    ))  # fmt: skip
                writer.append(split, _to_record(cfg, chunk, x))
                rows[split] += chunk.num_rows
                num_chunks += 1
                num_retried += retried
    return BuildSummary(
        path=str(path),
        rows=rows,
        units={s: [int(u) for u in plan.units[s]] for s in SPLITS},
        num_chunks=num_chunks,
        num_retried=num_retried,
    )
