"""The data as the diagnosis sees it: sorted rows, spline bases per unit, noise.

:func:`prepare_data` turns a :class:`~jaxcal.data.dataset.Dataset` (time = cycle) and
a :class:`~jaxcal.model.Model` into a
:class:`~jaxcal.diagnosis.data.loop_data.LoopData`: rows sorted by
(unit, time), an optional even subsample, the outputs of the residual ("sensors"), a
clamped cubic B-spline basis in time for each unit (the declared parameters are
``theta_u(c) = nominal + scale sum_k B_k(c) a_uk``: time-varying, smooth, and cheap to
fit jointly with constant effects) and the drift time ``tau``.

Outputs left out of the residual, with the reason recorded: those the model calls
uninformative (``DiagnosisHints.uninformative``, e.g. the turbofan's controller-set fan
speeds), columns the model does not output, constant ones and, when the noise is
estimated, quantised ones (the rounding step dominates the noise). A condition just
outside the model's valid range (by less than
:data:`jaxcal.data.dataset.JITTER_FRACTION` of the range, e.g. Mach -0.0005 of a
static point) is clipped onto the bound, and the note says so.

Noise: a :class:`~jaxcal.diagnosis.residuals.noise.NoiseModel` per output, white at the
known std when given (synthetic data) or at the model's reference level
(``DiagnosisHints.noise_rel``, default 1 % of the mean ``|x|``) until
:func:`jaxcal.diagnosis.residuals.noise.fit_noise` replaces it (level and AR colour)
after a first calibration.

Rows: a row with a non-finite condition is dropped and counted; a row with some
outputs missing (NaN) is kept, its missing entries marked in ``observed`` and left out
of the residual and the signatures (a sensor channel that dropped out); a row with
no output at all is dropped. A model with memory is never subsampled: its states are
simulated along every row (``max_rows`` is ignored, and a note says so).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy.interpolate import BSpline

from jaxcal.data.dataset import Dataset, clip_jitter
from jaxcal.diagnosis.data.loop_data import LoopData
from jaxcal.diagnosis.kinds.table import TAU_CYCLES
from jaxcal.diagnosis.residuals.noise import NoiseModel
from jaxcal.model import Model

MIN_DISTINCT = 20  # fewer distinct values: a setting or a heavily rounded output
DEFAULT_NOISE_REL = 0.01  # start noise std / mean |x| when the model gives none


def spline_basis(cycle: np.ndarray, num_knots: int) -> np.ndarray:
    """Clamped B-spline basis on ``[min(cycle), max(cycle)]``, ``K`` functions.

    Cubic when ``K >= 4`` (degree ``K - 1`` below); ``K = 1`` is a constant. A unit
    with a single time step gets the constant in its first column (the others stay
    zero).

    Args:
        cycle: ``[n]`` times (cycles) of one unit.
        num_knots: ``K >= 1``.

    Returns:
        ``[n, K]`` basis values (rows sum to 1).
    """
    if num_knots < 1:
        raise ValueError(f"knots must be >= 1, got {num_knots}")
    cycle = np.asarray(cycle, np.float64)
    out = np.zeros((cycle.shape[0], num_knots))
    lo, hi = float(cycle.min()), float(cycle.max())
    if num_knots == 1 or hi <= lo:
        out[:, 0] = 1.0
        return out
    degree = min(3, num_knots - 1)
    inner = np.linspace(lo, hi, num_knots - degree + 1)
    knots = np.concatenate([[lo] * degree, inner, [hi] * degree])
    out[:] = BSpline.design_matrix(np.clip(cycle, lo, hi), knots, degree).toarray()
    return out


def _select_sensors(data: Dataset, model: Model, sensors) -> tuple[list, dict]:
    excluded = {}
    uninformative = model.diagnosis.uninformative or {}
    if sensors is None:
        chosen = []
        for s in data.output_names:
            if s in uninformative:
                excluded[s] = uninformative[s]
            elif s not in model.output_names:
                excluded[s] = f"not an output of the model {model.name!r}"
            else:
                chosen.append(s)
    else:
        chosen = list(sensors)
        bad = [
            s
            for s in chosen
            if s not in data.output_names or s not in model.output_names
        ]
        if bad:
            valid = [s for s in data.output_names if s in model.output_names]
            raise ValueError(
                f"outputs {bad} are not in both the data and the model's outputs; "
                f"valid: {valid}"
            )
    return chosen, excluded


def _subsample(
    unit: np.ndarray, starts: np.ndarray, max_rows: int | None
) -> tuple[np.ndarray, int]:
    """The rows kept, one in ``stride`` of each unit's, and ``stride`` (1: all)."""
    n = unit.shape[0]
    if max_rows is None or n <= max_rows:
        return np.arange(n), 1
    if max_rows < len(starts) - 1:
        raise ValueError(f"max_rows={max_rows} is below the number of units")
    stride = int(np.ceil(n / max_rows))
    bounds = zip(starts[:-1], starts[1:], strict=True)
    return np.concatenate([np.arange(a, b, stride) for a, b in bounds]), stride


def prepare_data(
    data: Dataset,
    model: Model,
    *,
    sensors: Sequence[str] | None = None,
    units: Sequence[int] | None = None,
    max_rows: int | None = None,
    knots: int = 6,
    candidate_knots: int = 3,
    noise_std: Mapping[str, float] | np.ndarray | None = None,
    dropped_rows: int | None = None,
) -> LoopData:
    """Select, sort and subsample a data set for the diagnosis.

    Args:
        data: the rows (``time`` is the cycle index).
        model: the model whose conditions and outputs the columns name.
        sensors: outputs of the residual (``None``: all usable ones).
        units: unit ids to keep (``None``: all).
        max_rows: keep at most about this many rows (even stride within units).
        knots: B-spline functions per unit for the declared parameters.
        candidate_knots: B-spline functions per unit for candidate parameters.
        noise_std: known noise std, by output name or ``[S]`` in the chosen order;
            ``None``: a reference level now, to be estimated after a first fit.
        dropped_rows: rows the reader dropped for NaN / Inf (``None``: not counted).

    Returns:
        :class:`LoopData`; rows with NaN / Inf in w or a chosen output are dropped
        and counted per column in ``dropped`` (with those the reader dropped).
    """
    if units is not None:
        data = data.select_units(units)
    data, chosen, excluded, x_all = _usable_outputs(data, model, sensors, noise_std)
    finite, dropped = _finite_rows(data, model, chosen, x_all)
    notes = []
    order = _row_order(data, model, finite, max_rows, notes)
    unit_ids, first, unit = np.unique(
        data.unit[order], return_index=True, return_inverse=True
    )
    starts = np.append(first, order.size)
    cycle = data.time[order].astype(np.float64)
    tau, basis, basis_c = _time_bases(cycle, starts, knots, candidate_knots)
    x = x_all[order]
    observed = np.isfinite(x)
    notes += _partial_rows_note(observed, chosen)
    w, clip_notes = clip_jitter(data.w[order], model)
    notes = list(clip_notes) + notes
    if dropped_rows is None and not data.dropped:
        dropped_rows = 0  # the reader dropped nothing, so the count is known
    if dropped_rows is not None:
        dropped_rows = dropped_rows + int(finite.size - finite.sum())
    return LoopData(
        w=w,
        x=np.where(observed, x, 0.0),
        sensor_names=tuple(chosen),
        sensor_idx=np.array(model.output_index(chosen)),
        unit=unit.astype(np.int64),
        unit_ids=unit_ids,
        starts=starts,
        cycle=cycle,
        tau=tau,
        basis=basis,
        basis_candidate=basis_c,
        noise=_start_noise(model, chosen, x, noise_std),
        observed=observed,
        theta_true=None if data.theta is None else data.theta[order],
        row_index=data.row[order],
        excluded=excluded,
        notes=tuple(notes),
        dropped=dropped,
        dropped_rows=dropped_rows,
        condition_names=model.condition_names,
        condition_units=tuple(v.unit for v in model.conditions),
        sensor_units=tuple(model.unit_of(s) for s in chosen),
        parameter_names=model.parameter_names,
        parameter_nominal=model.nominal,
        theta_names=tuple(data.theta_names) if data.theta is not None else (),
    )


def _usable_outputs(data: Dataset, model: Model, sensors, noise_std):
    """The outputs of the residual and why the others are left out.

    Returns:
        ``(data for the model, chosen names, {output: reason}, x [N, S] of the
        chosen)``; constant outputs and, when the noise is to be estimated,
        heavily rounded ones (the rounding step would dominate the noise) are out.
    """
    chosen, excluded = _select_sensors(data, model, sensors)
    if not chosen:
        raise ValueError(f"no usable output in the data; excluded: {excluded}")
    data = data.for_model(model, chosen)
    x_all = data.x
    for j, s in enumerate(list(chosen)):
        col = x_all[:, j][np.isfinite(x_all[:, j])]
        if col.size and np.ptp(col) == 0:
            excluded[s] = "constant in this data"
    if noise_std is None:
        for j, s in enumerate(chosen):
            if s not in excluded and np.unique(x_all[:, j]).size < MIN_DISTINCT:
                excluded[s] = f"fewer than {MIN_DISTINCT} distinct values (rounded)"
    keep = [j for j, s in enumerate(chosen) if s not in excluded]
    chosen = [chosen[j] for j in keep]
    if not chosen:
        raise ValueError(f"no usable output in the data; excluded: {excluded}")
    return data, chosen, excluded, x_all[:, keep]


def _finite_rows(data: Dataset, model: Model, chosen, x_all) -> tuple[np.ndarray, dict]:
    """``(finite [N] bool, dropped)``: a row is kept when its conditions and at least
    one output are finite (its missing outputs are marked in ``observed``: a sensor
    channel that dropped out); ``dropped`` adds, per column, the rows dropped here
    to those the reader dropped (a dropped row counts in every column it is bad in).
    """
    finite_w, finite_x = np.isfinite(data.w), np.isfinite(x_all)
    finite = finite_w.all(1) & finite_x.any(1)
    dropped = dict(data.dropped or {})
    for name, ok in zip(model.condition_names, finite_w.T, strict=True):
        if not ok.all():
            dropped[name] = dropped.get(name, 0) + int(ok.size - ok.sum())
    for name, ok in zip(chosen, finite_x.T, strict=True):
        if np.any(~finite & ~ok):
            dropped[name] = dropped.get(name, 0) + int(np.sum(~finite & ~ok))
    return finite, dropped


def _row_order(data: Dataset, model: Model, finite, max_rows, notes: list):
    """The kept rows sorted by (unit, time), evenly subsampled to about
    ``max_rows`` unless the model has memory (then a note says so, in ``notes``)."""
    order = np.lexsort((np.arange(data.num_rows), data.time, data.unit))
    order = order[finite[order]]
    if order.size == 0:
        raise ValueError("the data have no row with finite conditions and outputs")
    unit_raw = data.unit[order]
    _, first = np.unique(unit_raw, return_index=True)
    starts = np.append(first, order.size)
    if model.is_stateful and max_rows is not None and order.size > max_rows:
        notes.append(
            f"all {order.size} rows used (max_rows={max_rows} ignored): the states of "
            f"model {model.name!r} are simulated along every row"
        )
    elif max_rows is not None:
        kept, stride = _subsample(unit_raw, starts, max_rows)
        if kept.size < order.size:  # said: a user reading "100 units" expects all rows
            notes.append(
                f"{kept.size} of {order.size} rows used: one in {stride} of each "
                f"unit's rows (max_rows={max_rows}; 0 or None keeps every row)"
            )
        order = order[kept]
    return order


def _time_bases(cycle, starts, knots: int, candidate_knots: int):
    """Per unit: the drift time ``tau`` and the spline bases of the declared
    (``knots``) and candidate (``candidate_knots``) parameters, ``([N], [N, K],
    [N, Kc])``."""
    tau = np.empty_like(cycle)
    basis = np.empty((cycle.size, knots))
    basis_c = np.empty((cycle.size, candidate_knots))
    for u in range(starts.size - 1):
        sl = slice(starts[u], starts[u + 1])
        tau[sl] = (cycle[sl] - cycle[sl].min()) / TAU_CYCLES
        basis[sl] = spline_basis(cycle[sl], knots)
        basis_c[sl] = spline_basis(cycle[sl], candidate_knots)
    return tau, basis, basis_c


def _partial_rows_note(observed, chosen) -> list[str]:
    """The note on rows used with some outputs missing (none: no note)."""
    partial = int(np.sum(~observed.all(1)))
    if not partial:
        return []
    missing = {s: int(np.sum(~observed[:, j])) for j, s in enumerate(chosen)}
    return [
        f"{partial} rows with some outputs missing are used with the outputs they "
        "have (missing: " + ", ".join(f"{s} {n}" for s, n in missing.items() if n) + ")"
    ]


def reference_noise_rel(model: Model, outputs) -> np.ndarray:
    """``[S]`` the model's reference noise std over each output's mean ``|x|``
    (``DiagnosisHints.noise_rel``, else :data:`DEFAULT_NOISE_REL`)."""
    rel = model.diagnosis.noise_rel or {}
    return np.array([rel.get(s, DEFAULT_NOISE_REL) for s in outputs])


def _start_noise(model: Model, chosen, x, noise_std) -> NoiseModel:
    """White noise at the given std, or at the model's reference level (a share of
    the mean ``|x|``) until :func:`jaxcal.diagnosis.residuals.noise.fit_noise`
    estimates it."""
    if noise_std is None:
        std = reference_noise_rel(model, chosen) * np.nanmean(np.abs(x), axis=0)
        return NoiseModel.white(std, "reference")
    return NoiseModel.white(_given_noise(noise_std, chosen), "given")


def _given_noise(noise_std, chosen) -> np.ndarray:
    if isinstance(noise_std, Mapping):
        missing = [s for s in chosen if s not in noise_std]
        if missing:
            raise ValueError(f"noise_std has no entry for outputs {missing}")
        std = np.array([float(noise_std[s]) for s in chosen])
    else:
        std = np.asarray(noise_std, np.float64)
        if std.shape != (len(chosen),):
            raise ValueError(f"noise_std must be [S={len(chosen)}], got {std.shape}")
    if not np.all(np.isfinite(std) & (std > 0)):
        raise ValueError("noise_std must be finite and > 0 for every output")
    return std
