"""The HDF5 file of a fleet calibration: written chunk by chunk, atomically.

Layout (flat rows, like the N-CMAPSS input: only valid steps, units in ascending global
order, time order within a unit):

* ``unit [N]`` int64 unit id, ``step [N]`` int64 index of the row within its unit
  (after any input stride), ``cycle [N]`` int64 flight number when the source has it;
* ``theta [N, P]`` calibrated parameters, ``xhat [N, S]`` model outputs;
* ``valid [N]`` bool, ``reason [N]`` int32 when the caller passes the calibrator's
  flags: a row that is not valid was skipped (NaN, out of range; its theta repeats
  the unit's last valid one); ``reason`` indexes the ``reasons`` root attribute and
  the ``flagged`` root attribute counts the rows per reason;
* ``partial [N]`` bool when the caller passes it: some outputs of the row were missing
  (NaN; used on the observed ones if ``valid``, else skipped as ``x_partial``); the
  ``num_partial`` root attribute counts them;
* ``aux_<name> [N, ...]`` every per-step diagnostic of the calibrator (e.g.
  ``aux_theta_std``), and any per-step extra the caller passes (e.g. ``theta_true``);
* ``unit_id [U]``, ``unit_length [U]``, ``unit_theta_last [U, P]`` one row per unit;
* root attributes ``theta_names`` / ``sensor_names`` (JSON lists) and the caller's.

:class:`FleetResultWriter` appends each chunk to resizable datasets of a temporary file
in the destination directory and ``os.replace`` s it into place only when the ``with``
block ends without an exception, so a reader never sees a half-written file and a
failed run leaves any previous file untouched; the temporary file of a run killed
mid-way is removed by the next write to the same path
(:func:`jaxcal.runs.folder.make_temp`). Memory is one chunk.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence

import h5py
import numpy as np

from jaxcal.calibrators.interface import REASONS, count_reasons
from jaxcal.runs.atomic import make_temp, release_temp
from jaxcal.settings import check_output_path

_CHUNK_ROWS = 8192  # HDF5 chunk length of the growable datasets


class FleetResultWriter:
    """Appendable, atomic writer of fleet calibration results.

    Example::

        with FleetResultWriter("out.h5", theta_names=("HPT_eff_mod",),
                               sensor_names=("T24", "T30")) as writer:
            writer.append(unit_ids, mask, theta, xhat, aux=aux)

    Args:
        path: destination ``.h5`` (its missing folders are created); a folder, a
            path under a file or in an unwritable folder is an error at once.
        theta_names: the ``P`` parameter names (columns of ``theta``).
        sensor_names: the ``S`` sensor names (columns of ``xhat``).
        attrs: extra root attributes; dicts and lists are stored as JSON strings.
    """

    def __init__(
        self,
        path,
        *,
        theta_names: Sequence[str],
        sensor_names: Sequence[str],
        attrs: Mapping | None = None,
    ):
        self.path = os.fspath(path)
        # a folder, a path under a file or an unwritable folder: said before the
        # work whose results it would hold, not after
        check_output_path(self.path, "path")
        self._attrs = {
            "theta_names": json.dumps(list(theta_names)),
            "sensor_names": json.dumps(list(sensor_names)),
            "reasons": json.dumps(list(REASONS)),
        }
        for key, value in (attrs or {}).items():
            if isinstance(value, dict | list | tuple):
                value = json.dumps(value, sort_keys=True)
            self._attrs[str(key)] = value
        self._num_p, self._num_s = len(theta_names), len(sensor_names)
        self._file: h5py.File | None = None
        self._tmp: str | None = None
        self.num_rows = 0
        self.num_units = 0
        self.flagged: dict[str, int] = count_reasons(np.zeros(0, np.int32))
        self.num_partial = 0  # rows with missing outputs (``partial=`` of append)

    def __enter__(self) -> FleetResultWriter:
        check_output_path(self.path, "path")
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        fd, self._tmp = make_temp(self.path)
        os.close(fd)
        self._file = h5py.File(self._tmp, "w")
        for key, value in self._attrs.items():
            self._file.attrs[key] = value
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self._file is not None:
                if exc_type is None:
                    self._file.attrs["flagged"] = json.dumps(self.flagged)
                    self._file.attrs["num_partial"] = self.num_partial
                self._file.close()
            if exc_type is None:
                os.chmod(self._tmp, 0o644)  # mkstemp makes 0600; results are shared
                os.replace(self._tmp, self.path)
        finally:
            if self._tmp is not None:
                release_temp(self._tmp)
            self._file, self._tmp = None, None

    def _append(self, name: str, values: np.ndarray) -> None:
        if name not in self._file:
            self._file.create_dataset(
                name,
                shape=(0,) + values.shape[1:],
                maxshape=(None,) + values.shape[1:],
                dtype=values.dtype,
                chunks=(_CHUNK_ROWS,) + values.shape[1:],
            )
        dset = self._file[name]
        if dset.shape[1:] != values.shape[1:]:
            raise ValueError(
                f"{name}: rows of shape {values.shape[1:]} do not match the earlier "
                f"chunks' {dset.shape[1:]}"
            )
        start = dset.shape[0]
        dset.resize(start + values.shape[0], axis=0)
        dset[start:] = values

    def append(
        self,
        unit_ids: np.ndarray,
        mask: np.ndarray,
        theta: np.ndarray,
        xhat: np.ndarray,
        *,
        aux: Mapping[str, np.ndarray] | None = None,
        cycle: np.ndarray | None = None,
        extras: Mapping[str, np.ndarray] | None = None,
        valid: np.ndarray | None = None,
        reason: np.ndarray | None = None,
        partial: np.ndarray | None = None,
    ) -> None:
        """Append the real (unmasked) rows of ``u`` units.

        Args:
            unit_ids: ``[u]`` unit ids. mask: ``[u, T]`` bool validity.
            theta: ``[u, T, P]``. xhat: ``[u, T, S]``.
            aux: per-step diagnostics ``[u, T, ...]`` (written as ``aux_<name>``).
            cycle: ``[u, T]`` flight numbers, or ``None``.
            extras: more per-step arrays ``[u, T, ...]`` written under their names.
            valid: ``[u, T]`` flags of the calibrator (``CalOutput.valid``), written
                as a column and counted in ``self.flagged``.
            reason: ``[u, T]`` their reasons (``CalOutput.reason``), written as a
                column and counted in ``self.flagged``.
            partial: ``[u, T]`` rows with missing outputs (``CalOutput.partial``),
                written as a column and counted in ``self.num_partial``.
        """
        if self._file is None:
            raise ValueError("FleetResultWriter.append outside its `with` block")
        unit_ids, mask = np.asarray(unit_ids, np.int64), np.asarray(mask, bool)
        num_units, num_steps = mask.shape
        theta, xhat = np.asarray(theta), np.asarray(xhat)
        if (
            unit_ids.shape != (num_units,)
            or theta.shape != (num_units, num_steps, self._num_p)
            or xhat.shape != (num_units, num_steps, self._num_s)
        ):
            raise ValueError(
                f"append: expected unit_ids [u], theta [u, T, {self._num_p}], xhat "
                f"[u, T, {self._num_s}] for mask [u, T] = {mask.shape}; got "
                f"{unit_ids.shape}, {theta.shape}, {xhat.shape}"
            )
        per_step = {"theta": theta, "xhat": xhat}
        per_step.update({f"aux_{k}": v for k, v in (aux or {}).items()})
        per_step.update(extras or {})
        if cycle is not None:
            per_step["cycle"] = np.asarray(cycle, np.int64)
        if valid is not None:
            per_step["valid"] = np.asarray(valid, bool)
        if reason is not None:
            per_step["reason"] = np.asarray(reason, np.int32)
            for name, count in count_reasons(reason, mask).items():
                self.flagged[name] += count
        if partial is not None:
            per_step["partial"] = np.asarray(partial, bool)
            self.num_partial += int(np.sum(per_step["partial"] & mask))
        steps = np.broadcast_to(np.arange(num_steps), mask.shape)
        per_step["unit"] = np.broadcast_to(unit_ids[:, None], mask.shape)
        per_step["step"] = steps
        for name, values in per_step.items():
            values = np.asarray(values)
            if values.shape[:2] != mask.shape:
                raise ValueError(f"append: {name} must be [u, T, ...] = {mask.shape}")
            self._append(name, values[mask])
        lengths = mask.sum(axis=1)
        last = np.maximum(lengths - 1, 0)
        self._append("unit_id", unit_ids)
        self._append("unit_length", lengths.astype(np.int64))
        self._append("unit_theta_last", theta[np.arange(num_units), last])
        self.num_rows += int(lengths.sum())
        self.num_units += num_units


def read_results(path) -> tuple[dict[str, np.ndarray], dict]:
    """Load a results file written by :class:`FleetResultWriter`.

    Returns:
        ``(arrays, attrs)``: every dataset as a numpy array, and the root attributes
        (JSON strings decoded).
    """
    with h5py.File(os.fspath(path), "r") as f:
        arrays = {name: f[name][()] for name in f}
        attrs = {}
        for key, value in f.attrs.items():
            if isinstance(value, bytes):
                value = value.decode("utf-8")
            if isinstance(value, str):
                try:
                    value = json.loads(value)
                except json.JSONDecodeError:
                    pass
            attrs[key] = value
    return arrays, attrs
