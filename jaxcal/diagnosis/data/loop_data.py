"""The diagnosis's view of a data set: :class:`LoopData`, built by
:func:`jaxcal.diagnosis.data.prepare.prepare_data`.

Rows sorted by (unit, time) with their spline bases, the outputs of the residual, the
noise model, and what cleaning did; the copies the loop makes (other noise, fewer rows,
fewer outputs) are methods, so every field stays consistent with the others.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from jaxcal.diagnosis.residuals.noise import NoiseModel, positions


@dataclasses.dataclass(frozen=True, eq=False)
class LoopData:
    """Rows of one data set ready for fitting (numpy, sorted by unit then time).

    Attributes:
        w: ``[N, W]`` operating conditions (the model's order).
        x: ``[N, S]`` measured outputs of the residual.
        sensor_names: ``S`` output names; ``sensor_idx`` ``[S]`` their positions in
            the model output.
        unit: ``[N]`` unit position ``0..U-1``; ``unit_ids`` ``[U]`` the record ids.
        starts: ``[U + 1]`` row offsets: unit ``u`` is rows ``starts[u]:starts[u+1]``.
        cycle: ``[N]`` float cycle number.
        tau: ``[N]`` (cycle - first cycle of the unit) / 100 (``TAU_CYCLES``).
        basis: ``[N, K]`` B-spline basis of each row's time within its unit (the
            declared parameters).
        basis_candidate: ``[N, Kc]`` the smaller basis of candidate (undeclared)
            parameters: fewer functions, fewer degrees of freedom to pay for in BIC.
        noise: the :class:`~jaxcal.diagnosis.residuals.noise.NoiseModel`
            (``noise_std`` is its marginal std ``[S]``, ``noise_source`` how it was
            obtained).
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

    def whiten(self, arr: np.ndarray, outputs=None) -> np.ndarray:
        """Prewhiten and standardise ``arr [N, S, ...]`` (output units) with the
        noise model (:meth:`~jaxcal.diagnosis.residuals.noise.NoiseModel.whiten`);
        missing outputs count as zero. ``outputs``: ``arr`` holds these outputs
        alone (indices; each output is whitened on its own, so the same numbers)."""
        arr = np.asarray(arr, np.float64)
        observed, noise = self.observed, self.noise
        if outputs is not None:
            observed, noise = observed[:, list(outputs)], noise.take(outputs)
        if not observed.all():  # the whitening does not write into arr: no copy
            mask = observed.reshape(observed.shape + (1,) * (arr.ndim - 2))
            arr = np.where(mask, arr, 0.0)
        return noise.whiten(arr, self.position)

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
