"""Parameters that act in some units only: calibrated in their carriers, held elsewhere.

A diagnosis that finds an effect in some units only (a temperature sensor's step in
units 1 and 3 of 6) exports an extended model whose added parameter lists its
carriers (``model.diagnosis.carriers``, :mod:`jaxcal.models.extended`). Tracked in
every unit, the parameter soaks up noise and misfit in the clean ones: a reactor
fleet's clean units got false offsets of -0.13 to +0.33 K and a heat-of-reaction
error of 0.042 for 0.006. So :func:`jaxcal.calibrate` splits the fleet by what each
unit carries: each group of units is calibrated with the parameters it carries (a
clean unit exactly as with the base model), and the groups' rows are put back in the
data's order with every parameter's column; a parameter a unit does not carry reads
its nominal value (0, no effect) with std 0 there.

Each group is its own calibration: where the noise is not given, it is estimated
from that group's rows (the note says so); a compiled program serves each distinct
parameter set. The methods that calibrate a chosen set of parameters take part (the
UKF, least squares, E2E trained on the call); a trained policy fixes its parameters
in its run, and E2E given trained weights in them: they estimate every parameter in
every unit, as their training did.

The fleet command line (:mod:`jaxcal.fleet.per_unit`) splits its units with the same
:func:`unit_groups` and fills the held columns with :func:`widen`.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Sequence

import numpy as np

from jaxcal.calibrators.front.result import CalibrationResult
from jaxcal.calibrators.methods import get
from jaxcal.data.dataset import Dataset
from jaxcal.data.readers import read_dataset
from jaxcal.model import Model
from jaxcal.problem import Problem

READER_OPTIONS = ("rename", "ignore", "nonfinite")  # as front._READER_OPTIONS


def applies(model: Model, theta: Sequence[str] | None, method: str, options) -> bool:
    """Whether a calibration of ``model`` splits its units: some calibrated
    parameter has carriers and ``method`` calibrates a chosen set (module doc)."""
    carriers = model.diagnosis.carriers or {}
    names = model.parameter_names if theta is None else tuple(theta)
    if not get(method).chooses_parameters(options):
        return False
    return any(n in carriers for n in names)


def unit_groups(
    model: Model, names: Sequence[str], units: np.ndarray
) -> list[tuple[tuple[int, ...], tuple[str, ...]]]:
    """``[(unit ids, calibrated names)]``: the units of ``units`` grouped by the
    parameters of ``names`` they carry (a parameter without carriers: every unit).

    Raises:
        ValueError: naming the units that carry none of ``names``.
    """
    carriers = model.diagnosis.carriers or {}
    groups: dict[tuple[str, ...], list[int]] = {}
    for u in units.tolist():
        own = tuple(n for n in names if n not in carriers or u in carriers[n])
        groups.setdefault(own, []).append(int(u))
    if () in groups:
        raise ValueError(
            f"theta={list(names)}: unit(s) {groups[()]} carry none of these "
            f"parameters (the model's carriers: {dict(carriers)}); calibrate a "
            "parameter every unit has too"
        )
    return [(tuple(ids), own) for own, ids in groups.items()]


def nominal_values(model: Model, names: Sequence[str]) -> np.ndarray:
    """``[len(names)]`` the nominal values of the parameters ``names`` of ``model``."""
    by_name = {p.name: p.nominal for p in model.parameters}
    return np.asarray([by_name[k] for k in names], np.float64)


def widen(values, own: Sequence[str], names: Sequence[str], fill, axes: int = 1):
    """``values`` whose last ``axes`` axes run over the parameters ``own``, as
    arrays over ``names`` (a superset): the columns of ``own`` placed, the others
    ``fill`` (a held parameter: its nominal value, or a std of 0; one number, or
    ``[len(names)]`` per column). ``axes=2``: a covariance, rows and columns."""
    values = np.asarray(values)
    cols = np.asarray([list(names).index(k) for k in own], int)
    lead = values.shape[: values.ndim - axes]
    out = np.empty((*lead, *(len(names),) * axes), values.dtype)
    out[...] = np.asarray(fill, values.dtype)
    if axes == 1:
        out[..., cols] = values
    elif axes == 2:
        out[..., cols[:, None], cols[None, :]] = values
    else:
        raise ValueError(f"widen: axes must be 1 or 2, got {axes}")
    return out


def held_note(groups, names: Sequence[str]) -> str:
    """The note naming, for each group of :func:`unit_groups`, the parameters of
    ``names`` held at nominal in its units."""
    shown = "; ".join(
        f"{', '.join(n for n in names if n not in own)} held at nominal in unit(s) "
        f"{list(ids)}" for ids, own in groups if len(own) < len(names)
    )  # fmt: skip
    return f"per-unit parameters (the model's carriers): {shown}"


def calibrate_split(
    calibrate: Callable,
    model: Model,
    data,
    method: str,
    theta: Sequence[str] | None,
    noise,
    *,
    outputs: Sequence[str] | None,
    seed: int,
    progress: bool,
    options: dict,
) -> tuple[CalibrationResult | None, Dataset]:
    """``(result, data)``: ``calibrate`` (the front door) on each group of units
    (:func:`unit_groups`) with the parameters it carries, merged in the data's row
    order (module doc), a note naming the groups among its notes and on the
    console; ``result`` is ``None`` where every unit of ``data`` (read, the
    readers' ``options`` taken out) carries every parameter of ``theta``."""
    reader = {k: options.pop(k) for k in READER_OPTIONS if k in options}
    data = read_dataset(data, model, **reader)
    names = model.parameter_names if theta is None else tuple(theta)
    groups = unit_groups(model, names, data.units)
    if len(groups) == 1 and groups[0][1] == names:
        return None, data
    parts = []
    for ids, own in groups:
        rows = np.isin(data.unit, ids)
        res = calibrate(
            model, data.take(rows), method, list(own), noise, outputs=outputs,
            seed=seed, progress=progress, **options,
        )  # fmt: skip
        parts.append((rows, own, res))
    merged = merge(parts, names, model, data, outputs)
    note = held_note(groups, names)
    if merged.problem.noise_source != "given":
        noise_each = "; ".join(
            f"units {list(ids)}: "
            + ", ".join(f"{k}={v:.3g}" for k, v in res.noise.items())
            for (ids, _), (_, _, res) in zip(groups, parts, strict=True)
        )  # fmt: skip
        note += f"; noise estimated per group ({noise_each})"
    warnings.warn(f"jaxcal.calibrate: {note}", stacklevel=3)
    return dataclasses.replace(merged, notes=(note, *merged.notes)), data


def merge(
    parts, names: Sequence[str], model: Model, data: Dataset, outputs
) -> CalibrationResult:
    """One result with every parameter of ``names`` from the groups' ``parts``
    ``[(rows [N] bool, own names, result)]``: a parameter a group does not
    calibrate reads its nominal value with std 0 in that group's rows."""
    n, p = data.num_rows, len(names)
    first = parts[0][2]
    nominal = nominal_values(model, names)
    theta = np.tile(nominal.astype(first.theta.dtype), (n, 1))
    has_std = all(res.theta_std is not None for _, _, res in parts)
    std = np.zeros((n, p), first.theta.dtype) if has_std else None
    fields = {}
    for rows, own, res in parts:
        if res.theta.shape[0] != int(rows.sum()):
            raise RuntimeError(  # a calibration returns one row per row given
                f"a unit group's result has {res.theta.shape[0]} rows for "
                f"{int(rows.sum())}"
            )
        theta[rows] = widen(res.theta, own, names, nominal)
        if std is not None:
            std[rows] = widen(res.theta_std, own, names, 0.0)
        for field in ("states", "xhat", "valid", "reason", "unit", "time",
                      "partial", "misfit", "at_bound"):  # fmt: skip
            value = getattr(res, field)
            if value is None:
                continue
            if field not in fields:
                fields[field] = np.zeros((n, *value.shape[1:]), value.dtype)
            elif fields[field].dtype != value.dtype:  # reason strings of two widths
                fields[field] = fields[field].astype(np.result_type(
                    fields[field].dtype, value.dtype
                ))  # fmt: skip
            fields[field][rows] = value
    notes = tuple(dict.fromkeys(note for _, _, res in parts for note in res.notes))
    return dataclasses.replace(
        first, theta=theta, theta_std=std, theta_names=tuple(names), notes=notes,
        problem=_problem(parts, names, model, data, outputs),
        **{k: fields.get(k) for k in ("states", "partial", "misfit", "at_bound")},
        **{k: fields[k] for k in ("xhat", "valid", "reason", "unit", "time")},
    )  # fmt: skip


def _problem(parts, names, model, data, outputs) -> Problem:
    """The merged result's problem: that of a group calibrating every parameter of
    ``names``, else one built on the data with the first group's noise."""
    for _, own, res in parts:
        if tuple(own) == tuple(names):
            return res.problem
    first = parts[0][2].problem
    noise = dict(zip(first.output_names, first.noise_std.tolist(), strict=True))
    problem = Problem.build(
        model, data.for_model(model, outputs), theta=names, noise=noise
    )
    return dataclasses.replace(problem, noise_source=first.noise_source)
