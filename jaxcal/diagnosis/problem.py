"""The record as the diagnosis sees it: sorted rows, spline bases per unit, noise.

:func:`prepare_data` turns a :class:`~jaxcal.data.record.Record` into a
:class:`LoopData`: rows sorted by (unit, cycle), an optional even subsample, the sensors
of the residual, a clamped cubic B-spline basis in cycle for each unit (the declared
health modifiers are ``theta_u(c) = sum_k B_k(c) a_uk``: time-varying, smooth, and cheap
to fit jointly with constant effects) and the drift time ``tau``.

Sensors left out of the residual, with the reason recorded: controller-set ones (the
fan speed follows the TRA schedule, so Nf, NRf, Nf_dmd and PCNfR_dmd carry no
information about the engine), sensors the engine does not output, constant ones and,
when the noise is estimated, quantised ones (the rounding step dominates the noise).

Noise levels: known per-sensor std when given (synthetic data), else a reference level
until :func:`.noise.estimate_noise_std` replaces it after a first calibration.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.interpolate import BSpline

from jaxcal.data.record import Record
from jaxcal.diagnosis.effects import TAU_CYCLES
from jaxcal.diagnosis.noise import reference_noise_rel
from jaxcal.physics.constants import CONDITION_NAMES, SENSOR_NAMES

CONTROLLER_SET = ("Nf", "NRf", "Nf_dmd", "PCNfR_dmd")
MIN_DISTINCT = 20  # fewer distinct values: a setting or a heavily rounded output


@dataclasses.dataclass(frozen=True, eq=False)
class LoopData:
    """Rows of one record ready for fitting (numpy, sorted by unit then cycle).

    Attributes:
        w: ``[N, 4]`` operating conditions.
        x: ``[N, S]`` measured sensors of the residual.
        sensor_names: ``S`` names; ``sensor_idx`` their positions in the engine output.
        sensor_idx: ``[S]`` int.
        unit: ``[N]`` unit position ``0..U-1``; ``unit_ids`` ``[U]`` the record ids.
        unit_ids: ``[U]`` int.
        starts: ``[U + 1]`` row offsets: unit ``u`` is rows ``starts[u]:starts[u+1]``.
        cycle: ``[N]`` float cycle number.
        tau: ``[N]`` (cycle - first cycle of the unit) / 100 (``TAU_CYCLES``).
        basis: ``[N, K]`` B-spline basis of each row's cycle within its unit (the
            declared modifiers).
        basis_candidate: ``[N, Kc]`` the smaller basis of candidate (undeclared)
            modifiers: fewer functions, fewer degrees of freedom to pay for in BIC.
        noise_std: ``[S]`` sensor noise std (sensor units).
        noise_source: ``"given"``, ``"reference"`` or ``"estimated"``.
        theta_true: ``[N, 10]`` ground truth or ``None``.
        row_index: ``[N]`` row of the original record.
        excluded: sensor -> reason it is not in the residual.
        notes: what data cleaning did (clipped or dropped rows).
        dropped: column -> rows dropped for a NaN / Inf in that column, by the reader
            (``Record.dropped``) or here; a row bad in two columns counts in both.
        dropped_rows: rows dropped for NaN / Inf in total (each row once).
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
    noise_std: np.ndarray
    noise_source: str
    theta_true: np.ndarray | None
    row_index: np.ndarray
    excluded: dict[str, str]
    notes: tuple[str, ...] = ()
    dropped: dict[str, int] = dataclasses.field(default_factory=dict)
    dropped_rows: int = 0

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
        """Spline functions ``K`` per declared modifier."""
        return int(self.basis.shape[1])

    @property
    def num_candidate_knots(self) -> int:
        """Spline functions ``Kc`` per candidate modifier."""
        return int(self.basis_candidate.shape[1])

    def with_noise(self, noise_std: np.ndarray, source: str) -> LoopData:
        """A copy with other noise levels (``[S]``, all > 0)."""
        noise_std = np.asarray(noise_std, np.float64)
        if noise_std.shape != (self.num_sensors,) or not np.all(noise_std > 0):
            raise ValueError(f"noise_std must be [S={self.num_sensors}] and > 0")
        return dataclasses.replace(self, noise_std=noise_std, noise_source=source)

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

    def drop_sensors(self, reasons: Mapping[str, str]) -> LoopData:
        """A copy without the sensors in ``reasons`` (recorded in ``excluded``)."""
        keep = [j for j, s in enumerate(self.sensor_names) if s not in reasons]
        if not keep:
            raise ValueError(
                f"no sensor left in the residual; excluded: {dict(reasons)}"
            )
        return dataclasses.replace(
            self,
            x=self.x[:, keep],
            sensor_names=tuple(self.sensor_names[j] for j in keep),
            sensor_idx=self.sensor_idx[keep],
            noise_std=self.noise_std[keep],
            excluded={**self.excluded, **dict(reasons)},
        )


def spline_basis(cycle: np.ndarray, num_knots: int) -> np.ndarray:
    """Clamped B-spline basis on ``[min(cycle), max(cycle)]``, ``K`` functions.

    Cubic when ``K >= 4`` (degree ``K - 1`` below); ``K = 1`` is a constant. A unit
    with a single cycle gets the constant in its first column (the others stay zero).

    Args:
        cycle: ``[n]`` cycles of one unit.
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


def _select_sensors(record: Record, engine_sensors, sensors) -> tuple[list, dict]:
    excluded = {}
    if sensors is None:
        chosen = []
        for s in record.x_names:
            if s in CONTROLLER_SET:
                excluded[s] = "set by the fan-speed controller (TRA schedule)"
            elif s not in engine_sensors:
                excluded[s] = "not an output of the engine model"
            else:
                chosen.append(s)
    else:
        chosen = list(sensors)
        bad = [s for s in chosen if s not in record.x_names or s not in engine_sensors]
        if bad:
            valid = [s for s in record.x_names if s in engine_sensors]
            raise ValueError(
                f"sensors {bad} are not in both the record and the engine "
                f"outputs; valid: {valid}"
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
    record: Record,
    engine_sensors: Sequence[str] = SENSOR_NAMES,
    *,
    sensors: Sequence[str] | None = None,
    units: Sequence[int] | None = None,
    max_rows: int | None = None,
    knots: int = 6,
    candidate_knots: int = 3,
    noise_std: Mapping[str, float] | np.ndarray | None = None,
) -> LoopData:
    """Select, sort and subsample a record for the diagnosis.

    Args:
        record: the data.
        engine_sensors: the engine's ``sensor_names``.
        sensors: sensors of the residual (``None``: all usable ones).
        units: unit ids to keep (``None``: all).
        max_rows: keep at most about this many rows (even stride within units).
        knots: B-spline functions per unit for the declared parameters.
        candidate_knots: B-spline functions per unit for candidate modifiers.
        noise_std: known noise std, by sensor name or ``[S]`` in the chosen order;
            ``None``: a reference level now, to be estimated after a first fit.

    Returns:
        :class:`LoopData`; rows with NaN / Inf in w or a chosen sensor are dropped
        and counted per column in ``dropped`` (with those the reader dropped).
    """
    if units is not None:
        record = record.select_units(units)
    chosen, excluded = _select_sensors(record, engine_sensors, sensors)
    x_all = record.columns(chosen) if chosen else np.zeros((record.num_rows, 0))
    for j, s in enumerate(list(chosen)):
        col = x_all[:, j][np.isfinite(x_all[:, j])]
        if col.size and np.ptp(col) == 0:
            excluded[s] = "constant in this record"
    if noise_std is None:
        for j, s in enumerate(chosen):
            if s not in excluded and np.unique(x_all[:, j]).size < MIN_DISTINCT:
                excluded[s] = f"fewer than {MIN_DISTINCT} distinct values (rounded)"
    keep = [j for j, s in enumerate(chosen) if s not in excluded]
    chosen = [chosen[j] for j in keep]
    if not chosen:
        raise ValueError(f"no usable sensor in the record; excluded: {excluded}")
    x_all = x_all[:, keep]
    finite_w, finite_x = np.isfinite(record.w), np.isfinite(x_all)
    finite = finite_w.all(1) & finite_x.all(1)
    dropped = dict(record.dropped)
    for name, ok in zip(
        CONDITION_NAMES + tuple(chosen),
        np.concatenate([finite_w, finite_x], axis=1).T,
        strict=True,
    ):
        if not ok.all():
            dropped[name] = dropped.get(name, 0) + int(ok.size - ok.sum())
    order = np.lexsort((np.arange(record.num_rows), record.cycle, record.unit))
    order = order[finite[order]]
    if order.size == 0:
        raise ValueError("the record has no row with finite w and sensors")
    unit_raw = record.unit[order]
    unit_ids, first = np.unique(unit_raw, return_index=True)
    starts = np.append(first, order.size)
    order = order[_subsample(unit_raw, starts, max_rows)]
    unit_raw = record.unit[order]
    unit_ids, first, unit = np.unique(unit_raw, return_index=True, return_inverse=True)
    starts = np.append(first, order.size)
    cycle = record.cycle[order].astype(np.float64)
    tau = np.empty_like(cycle)
    basis = np.empty((order.size, knots))
    basis_c = np.empty((order.size, candidate_knots))
    for u in range(unit_ids.size):
        sl = slice(starts[u], starts[u + 1])
        tau[sl] = (cycle[sl] - cycle[sl].min()) / TAU_CYCLES
        basis[sl] = spline_basis(cycle[sl], knots)
        basis_c[sl] = spline_basis(cycle[sl], candidate_knots)
    x = x_all[order]
    w = record.w[order].copy()
    notes = []
    if np.any(w[:, 1] < 0):
        notes.append(
            f"Mach < 0 (jitter of a static condition) set to 0 on "
            f"{int(np.sum(w[:, 1] < 0))} rows"
        )
        w[:, 1] = np.maximum(w[:, 1], 0.0)
    if noise_std is None:
        std = np.array([reference_noise_rel(s) for s in chosen]) * np.abs(x).mean(0)
        source = "reference"
    else:
        std, source = _given_noise(noise_std, chosen), "given"
    return LoopData(
        w=w,
        x=x,
        sensor_names=tuple(chosen),
        sensor_idx=np.array([list(engine_sensors).index(s) for s in chosen]),
        unit=unit.astype(np.int64),
        unit_ids=unit_ids,
        starts=starts,
        cycle=cycle,
        tau=tau,
        basis=basis,
        basis_candidate=basis_c,
        noise_std=std,
        noise_source=source,
        theta_true=None if record.theta is None else record.theta[order],
        row_index=order,
        excluded=excluded,
        notes=tuple(notes),
        dropped=dropped,
        dropped_rows=record.dropped_rows + int(finite.size - finite.sum()),
    )


def _given_noise(noise_std, chosen) -> np.ndarray:
    if isinstance(noise_std, Mapping):
        missing = [s for s in chosen if s not in noise_std]
        if missing:
            raise ValueError(f"noise_std has no entry for sensors {missing}")
        std = np.array([float(noise_std[s]) for s in chosen])
    else:
        std = np.asarray(noise_std, np.float64)
        if std.shape != (len(chosen),):
            raise ValueError(f"noise_std must be [S={len(chosen)}], got {std.shape}")
    if not np.all(np.isfinite(std) & (std > 0)):
        raise ValueError("noise_std must be finite and > 0 for every sensor")
    return std
