"""A fleet run of a model whose parameters act in some units only.

An extended model's effect found in some units only lists its carriers
(``model.diagnosis.carriers``, :mod:`jaxcal.models.extended`). As in
:func:`jaxcal.calibrate` (:mod:`jaxcal.calibrators.front.carriers`, whose
:func:`~jaxcal.calibrators.front.carriers.unit_groups` splits the units here too), each
group of units is calibrated with the parameters it carries, and a parameter a unit does
not carry reads its nominal value (0: no effect) with std 0 in that unit's rows of the
file, whose columns stay every parameter (:class:`WidenedWriter`). Every group's problem
is the fleet's (the same data sample, noise and normalisation; only the calibrated
parameters differ), so a unit is calibrated exactly as a run of the same command with
``theta=`` its group's parameters; a policy, trained on its parameters, estimates them
in every unit (:func:`~jaxcal.calibrators.front.carriers.applies`).

The file keeps its order, units in ascending id: consecutive units of one group form a
:class:`UnitRun`, streamed in chunks as the whole fleet would be, with its group's
calibrator (one compiled program per group). Every process plans the same runs from the
selected unit ids and the model's carriers, so the runs' collectives (run, gather) come
in the same order in every process. A run shorter than a chunk is padded with dummy
units, so carriers scattered among the units cost up to two chunks more per run of
carriers.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import numpy as np

from jaxcal.calibrators.front import carriers
from jaxcal.calibrators.interface import count_reasons
from jaxcal.fleet.streaming import calibrate_stream, stream_summary
from jaxcal.model import Model

# per-step diagnostics over the calibrated parameters: name -> parameter axes
PARAMETER_AUX = {"theta_std": 1, "laplace_std": 1, "theta_cov": 2}


class UnitRun(NamedTuple):
    """Consecutive units (ascending ids) calibrated with the parameters ``theta``."""

    unit_ids: np.ndarray
    theta: tuple[str, ...]


def plan_runs(
    model: Model,
    theta: Sequence[str],
    unit_ids: np.ndarray,
    method: str,
    options: Mapping,
) -> tuple[list[UnitRun], str | None]:
    """``(runs, note)``: the units of ``unit_ids`` (ascending) in runs of one group
    each (module doc), and the note naming the held parameters (``None``: one run of
    every unit with every parameter of ``theta``).

    Raises:
        ValueError: naming the units that carry none of ``theta``.
    """
    theta, unit_ids = tuple(theta), np.asarray(unit_ids, np.int64)
    if not carriers.applies(model, theta, method, dict(options)):
        return [UnitRun(unit_ids, theta)], None
    groups = carriers.unit_groups(model, theta, unit_ids)
    if len(groups) == 1 and groups[0][1] == theta:
        return [UnitRun(unit_ids, theta)], None
    own_of = {u: own for ids, own in groups for u in ids}
    runs: list[tuple[list[int], tuple[str, ...]]] = []
    for u in unit_ids.tolist():
        if runs and runs[-1][1] == own_of[u]:
            runs[-1][0].append(u)
        else:
            runs.append(([u], own_of[u]))
    plan = [UnitRun(np.asarray(ids, np.int64), own) for ids, own in runs]
    return plan, carriers.held_note(groups, theta)


class WidenedWriter:
    """A :class:`~jaxcal.fleet.results.FleetResultWriter` fed by a run that
    calibrates ``own`` of the file's parameters ``names``: ``theta`` and the
    per-parameter diagnostics (:data:`PARAMETER_AUX`) get every column, a held
    parameter its ``nominal`` value and a std (a covariance) of 0."""

    def __init__(self, writer, own: Sequence[str], names: Sequence[str], nominal):
        self.writer, self.own, self.names = writer, tuple(own), tuple(names)
        self.nominal = np.asarray(nominal, np.float64)

    def append(self, unit_ids, mask, theta, xhat, *, aux=None, **rest) -> None:
        """:meth:`FleetResultWriter.append` with the held columns filled."""
        theta = carriers.widen(theta, self.own, self.names, self.nominal)
        wide = {
            k: carriers.widen(v, self.own, self.names, 0.0, PARAMETER_AUX[k])
            if k in PARAMETER_AUX else v
            for k, v in (aux or {}).items()
        }  # fmt: skip
        self.writer.append(unit_ids, mask, theta, xhat, aux=wide, **rest)


def merge_stats(parts: Sequence[dict]) -> dict:
    """One :func:`~jaxcal.fleet.streaming.calibrate_stream` summary of the runs'."""
    counts = {
        k: sum(p[k] for p in parts)
        for k in ("num_chunks", "num_units", "num_rows", "num_partial")
    }
    flagged = count_reasons([])
    for part in parts:
        for name, count in part["flagged"].items():
            flagged[name] += count
    return stream_summary(counts, flagged, sum(p["seconds"] for p in parts))


def stream_runs(
    runs: Sequence[UnitRun],
    fleets: Mapping,
    source,
    mesh,
    *,
    theta_names: Sequence[str],
    nominal,
    chunk_units: int,
    size: int,
    unroll: int = 1,
    writer=None,
) -> dict:
    """Calibrate the ``runs`` in unit order, each with its group's method; append
    to ``writer`` with every parameter of ``theta_names`` (process 0's; ``None``
    elsewhere). Collective: every process calls it with the same runs.

    Args:
        runs: from :func:`plan_runs`.
        fleets: a run's ``theta`` -> its :class:`~jaxcal.fleet.method.FleetMethod`.
        source: the :class:`~jaxcal.fleet.sources.FleetSource`.
        mesh: from :func:`~jaxcal.fleet.sharded.make_unit_mesh`.
        theta_names: the file's parameters; nominal: their nominal values.
        chunk_units, size, unroll: as :func:`~jaxcal.fleet.streaming.calibrate_stream`
            (``size``: padded units per process and chunk).

    Returns:
        The summary of :func:`~jaxcal.fleet.streaming.calibrate_stream` over every run.
    """
    theta_names = tuple(theta_names)
    parts = []
    for run in runs:
        fleet = fleets[run.theta]
        chunks = source.chunks(
            theta_names, chunk_units, jax.process_index(), jax.process_count(),
            units=run.unit_ids,
        )  # fmt: skip
        out = writer
        if writer is not None and run.theta != theta_names:
            out = WidenedWriter(writer, run.theta, theta_names, nominal)
        parts.append(calibrate_stream(
            fleet.calibrator, chunks, mesh, size=size, writer=out, unroll=unroll,
            check=fleet.check,
        ))  # fmt: skip
    return merge_stats(parts)
