"""The data as the diagnosis sees it: sorted rows, spline bases per unit, noise.

:func:`prepare_data` turns a :class:`~jaxcal.data.dataset.Dataset` (time = cycle) and
a :class:`~jaxcal.model.Model` into a :class:`LoopData`: rows sorted by (unit, time),
an optional even subsample, the outputs of the residual ("sensors"), a clamped cubic
B-spline basis in time for each unit (the declared parameters are ``theta_u(c) =
nominal + scale sum_k B_k(c) a_uk``: time-varying, smooth, and cheap to fit jointly
with constant effects) and the drift time ``tau``.

Outputs left out of the residual, with the reason recorded: those the model calls
uninformative (``DiagnosisHints.uninformative``, e.g. the turbofan's controller-set fan
speeds), columns the model does not output, constant ones and, when the noise is
estimated, quantised ones (the rounding step dominates the noise). A condition just
outside the model's valid range (by less than
:data:`jaxcal.data.dataset.JITTER_FRACTION` of the range, e.g. Mach -0.0005 of a
static point) is clipped onto the bound, and the note says so.

Noise: a :class:`~jaxcal.diagnosis.noise.NoiseModel` per output, white at the known
std when given (synthetic data) or at the model's reference level
(``DiagnosisHints.noise_rel``, default 1 % of the mean ``|x|``) until
:func:`.noise.fit_noise` replaces it (level and AR colour) after a first calibration.

Rows: a row with a non-finite condition is dropped and counted; a row with some
outputs missing (NaN) is kept, its missing entries marked in ``observed`` and left out
of the residual and the signatures (a sensor channel that dropped out); a row with
no output at all is dropped. A model with memory is never subsampled: its states are
simulated along every row (``max_rows`` is ignored, and a note says so).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.interpolate import BSpline

from jaxcal.data.dataset import Dataset, clip_jitter
from jaxcal.diagnosis.kinds import TAU_CYCLES
from jaxcal.diagnosis.noise import NoiseModel, positions
from jaxcal.model import Model

MIN_DISTINCT = 20  # fewer distinct values: a setting or a heavily rounded output
DEFAULT_NOISE_REL = 0.01  # start noise std / mean |x| when the model gives none


@dataclasses.dataclass(frozen=True, eq=False)
class LoopData:
    """Rows of one data set ready for fitting (numpy, sorted by unit then time).

    Attributes:
        w: ``[N, W]`` operating conditions (the model's order).
        x: ``[N, S]`` measured outputs of the residual.
        sensor_names: ``S`` output names; ``sensor_idx`` their positions in the
            model output.
        sensor_idx: ``[S]`` int.
        unit: ``[N]`` unit position ``0..U-1``; ``unit_ids`` ``[U]`` the record ids.
        unit_ids: ``[U]`` int.
        starts: ``[U + 1]`` row offsets: unit ``u`` is rows ``starts[u]:starts[u+1]``.
        cycle: ``[N]`` float cycle number.
        tau: ``[N]`` (cycle - first cycle of the unit) / 100 (``TAU_CYCLES``).
        basis: ``[N, K]`` B-spline basis of each row's time within its unit (the
            declared parameters).
        basis_candidate: ``[N, Kc]`` the smaller basis of candidate (undeclared)
            parameters: fewer functions, fewer degrees of freedom to pay for in BIC.
        noise: the :class:`~jaxcal.diagnosis.noise.NoiseModel` (``noise_std`` is
            its marginal std ``[S]``, ``noise_source`` how it was obtained).
        observed: ``[N, S]`` bool, False where an output is missing in a row.
        theta_true: ``[N, len(theta_names)]`` ground truth or ``None``.
        row_index: ``[N]`` row of the data set (``Dataset.take`` order).
        excluded: output -> reason it is not in the residual.
        notes: what data cleaning did (clipped or dropped rows).
        dropped: column -> rows dropped for a NaN / Inf in that column, by the reader
            (``Dataset.dropped``) or here; a row bad in two columns counts in both.
        dropped_rows: rows dropped for NaN / Inf in total (each row once), or
            ``None`` when the reader did not count them.
        condition_names: ``W`` condition names; ``parameter_names`` and
            ``parameter_nominal`` the model's ``P_all`` parameters and nominal
            values; ``theta_names`` the columns of ``theta_true``.
        sensor_units, condition_units: the model's units of those names.
    """

    w: np.ndarray
    x: np.ndarray
    sensor_names: tuple[str, ...]
    sensor_idx: np.ndarray
    unit: np.ndarray
    unit_ids: np.ndarray
    starts: np.ndarray
    cycle: np.ndarray
    tau: np.ndarray
    basis: np.ndarray
    basis_candidate: np.ndarray
    noise: NoiseModel
    observed: np.ndarray
    theta_true: np.ndarray | None
    row_index: np.ndarray
    excluded: dict[str, str]
    notes: tuple[str, ...] = ()
    dropped: dict[str, int] = dataclasses.field(default_factory=dict)
    dropped_rows: int | None = 0
    condition_names: tuple[str, ...] = ()
    condition_units: tuple[str, ...] = ()
    sensor_units: tuple[str, ...] = ()
    parameter_names: tuple[str, ...] = ()
    parameter_nominal: np.ndarray | None = None
    theta_names: tuple[str, ...] = ()

    @property
    def noise_std(self) -> np.ndarray:
        """``[S]`` marginal noise std (output units)."""
        return self.noise.sigma

    @property
    def noise_source(self) -> str:
        """``given``, ``reference`` or ``estimated``."""
        return self.noise.source

    @property
    def position(self) -> np.ndarray:
        """``[N]`` rows since the unit's first row."""
        return positions(self.starts, self.num_rows)

    def whiten(self, arr: np.ndarray) -> np.ndarray:
        """Prewhiten and standardise ``arr [N, S, ...]`` (output units) with the
        noise model (:meth:`~jaxcal.diagnosis.noise.NoiseModel.whiten`); missing
        outputs count as zero."""
        arr = np.asarray(arr, np.float64)
        mask = self.observed.reshape(self.observed.shape + (1,) * (arr.ndim - 2))
        return self.noise.whiten(np.where(mask, arr, 0.0), self.position)

    @property
    def num_rows(self) -> int:
        """Rows ``N``."""
        return int(self.x.shape[0])

    @property
    def num_sensors(self) -> int:
        """Sensors ``S`` of the residual."""
        return int(self.x.shape[1])

    @property
    def num_units(self) -> int:
        """Units ``U``."""
        return int(self.unit_ids.shape[0])

    @property
    def num_knots(self) -> int:
        """Spline functions ``K`` per declared parameter."""
        return int(self.basis.shape[1])

    @property
    def num_candidate_knots(self) -> int:
        """Spline functions ``Kc`` per candidate parameter."""
        return int(self.basis_candidate.shape[1])

    def with_noise(self, noise: NoiseModel) -> LoopData:
        """A copy with another noise model (levels ``[S]``, all > 0)."""
        if noise.sigma.shape != (self.num_sensors,) or not np.all(noise.sigma > 0):
            raise ValueError(f"noise std must be [S={self.num_sensors}] and > 0")
        return dataclasses.replace(self, noise=noise)

    def take_rows(self, keep: np.ndarray, note: str) -> LoopData:
        """A copy with the rows ``keep`` (bool ``[N]``); units left empty disappear."""
        keep = np.asarray(keep, bool)
        if not keep.any():
            raise ValueError(f"no row left: {note}")
        unit_ids, first, unit = np.unique(
            self.unit_ids[self.unit[keep]], return_index=True, return_inverse=True
        )
        return dataclasses.replace(
            self,
            w=self.w[keep],
            x=self.x[keep],
            observed=self.observed[keep],
            unit=unit.astype(np.int64),
            unit_ids=unit_ids,
            starts=np.append(first, int(keep.sum())),
            cycle=self.cycle[keep],
            tau=self.tau[keep],
            basis=self.basis[keep],
            basis_candidate=self.basis_candidate[keep],
            theta_true=None if self.theta_true is None else self.theta_true[keep],
            row_index=self.row_index[keep],
            notes=self.notes + (note,),
        )

    def mask_rows(self, keep: np.ndarray, note: str) -> LoopData:
        """A copy whose rows outside ``keep`` are left out of the residual but kept
        in time (a model with memory is simulated through them)."""
        keep = np.asarray(keep, bool)
        if not keep.any():
            raise ValueError(f"no row left: {note}")
        observed = self.observed & keep[:, None]
        return dataclasses.replace(self, observed=observed, notes=self.notes + (note,))

    def drop_sensors(self, reasons: Mapping[str, str]) -> LoopData:
        """A copy without the sensors in ``reasons`` (recorded in ``excluded``)."""
        keep = [j for j, s in enumerate(self.sensor_names) if s not in reasons]
        if not keep:
            raise ValueError(
                f"no output left in the residual; excluded: {dict(reasons)}"
            )
        return dataclasses.replace(
            self,
            x=self.x[:, keep],
            observed=self.observed[:, keep],
            sensor_names=tuple(self.sensor_names[j] for j in keep),
            sensor_idx=self.sensor_idx[keep],
            noise=self.noise.take(keep),
            sensor_units=tuple(self.sensor_units[j] for j in keep),
            excluded={**self.excluded, **dict(reasons)},
        )


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
) -> np.ndarray:
    n = unit.shape[0]
    if max_rows is None or n <= max_rows:
        return np.arange(n)
    if max_rows < len(starts) - 1:
        raise ValueError(f"max_rows={max_rows} is below the number of units")
    stride = int(np.ceil(n / max_rows))
    return np.concatenate(
        [np.arange(a, b, stride) for a, b in zip(starts[:-1], starts[1:], strict=True)]
    )


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
    x_all = x_all[:, keep]
    finite_w, finite_x = np.isfinite(data.w), np.isfinite(x_all)
    # a row is kept when its conditions and at least one output are finite; its
    # missing outputs are marked in `observed` (a sensor channel that dropped out)
    finite = finite_w.all(1) & finite_x.any(1)
    dropped = dict(data.dropped or {})
    for name, ok in zip(model.condition_names, finite_w.T, strict=True):
        if not ok.all():
            dropped[name] = dropped.get(name, 0) + int(ok.size - ok.sum())
    for name, ok in zip(chosen, finite_x.T, strict=True):  # a dropped row counts
        if np.any(~finite & ~ok):  # in every column it is bad in
            dropped[name] = dropped.get(name, 0) + int(np.sum(~finite & ~ok))
    order = np.lexsort((np.arange(data.num_rows), data.time, data.unit))
    order = order[finite[order]]
    if order.size == 0:
        raise ValueError("the data have no row with finite conditions and outputs")
    unit_raw = data.unit[order]
    unit_ids, first = np.unique(unit_raw, return_index=True)
    starts = np.append(first, order.size)
    notes = []
    if model.is_stateful and max_rows is not None and order.size > max_rows:
        notes.append(
            f"all {order.size} rows used (max_rows={max_rows} ignored): the states of "
            f"model {model.name!r} are simulated along every row"
        )
    elif max_rows is not None:
        order = order[_subsample(unit_raw, starts, max_rows)]
    unit_raw = data.unit[order]
    unit_ids, first, unit = np.unique(unit_raw, return_index=True, return_inverse=True)
    starts = np.append(first, order.size)
    cycle = data.time[order].astype(np.float64)
    tau = np.empty_like(cycle)
    basis = np.empty((order.size, knots))
    basis_c = np.empty((order.size, candidate_knots))
    for u in range(unit_ids.size):
        sl = slice(starts[u], starts[u + 1])
        tau[sl] = (cycle[sl] - cycle[sl].min()) / TAU_CYCLES
        basis[sl] = spline_basis(cycle[sl], knots)
        basis_c[sl] = spline_basis(cycle[sl], candidate_knots)
    x = x_all[order]
    observed = np.isfinite(x)
    partial = int(np.sum(~observed.all(1)))
    if partial:
        missing = {s: int(np.sum(~observed[:, j])) for j, s in enumerate(chosen)}
        notes.append(
            f"{partial} rows with some outputs missing are used with the outputs they "
            "have (missing: "
            + ", ".join(f"{s} {n}" for s, n in missing.items() if n)
            + ")"
        )
    w, clip_notes = clip_jitter(data.w[order], model)
    notes = list(clip_notes) + notes
    if noise_std is None:
        rel = model.diagnosis.noise_rel or {}
        std = np.array([rel.get(s, DEFAULT_NOISE_REL) for s in chosen])
        std = std * np.nanmean(np.abs(x), axis=0)
        noise = NoiseModel.white(std, "reference")
    else:
        noise = NoiseModel.white(_given_noise(noise_std, chosen), "given")
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
        noise=noise,
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
