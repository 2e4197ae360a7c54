"""What :func:`jaxcal.calibrate` returns: per-row estimates with their names.

Kept in the data's row order, with the problem that was solved; ``to_frame`` gives a
pandas table, ``summary`` the last estimate of each unit, ``plot`` a figure.

``save`` keeps a result as one Parquet file, an open format any Parquet reader takes:
the columns of ``to_frame`` and, in the schema's metadata under :data:`META_KEY`, a
JSON object with everything else (method, names, the units of the parameters, outputs
and states, notes, noise source, ``problem.to_json()``, and each field's column names
and numpy dtype, so that ``load`` restores every field exactly). A loaded result gets
its :class:`~jaxcal.problem.Problem` back only when given the model (the file stores
the model's name, not its code); without it ``problem`` is ``None`` and the rest,
``noise_source`` and the units included, comes from the file.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from jaxcal.models import load as load_model
from jaxcal.problem import Problem
from jaxcal.runs.atomic import write_atomic_with
from jaxcal.settings import check_output_path

META_KEY = b"jaxcal.result"  # the Parquet schema-metadata key of a saved result
FORMAT_VERSION = 1
_ARRAYS = ("theta", "theta_std", "states", "xhat", "unit", "time", "valid", "reason")
_OPTIONAL = ("partial", "misfit", "at_bound")  # fields that may be None


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Per-row results of :func:`calibrate`, in the data's row order.

    Attributes:
        theta: ``[N, P]`` calibrated parameters after each row.
        theta_std: ``[N, P]`` their standard deviation, or ``None``.
        states: ``[N, Z]`` the model's hidden state after each row (the joint UKF's
            filtered state, the window fit's simulated one), or ``None``.
        state_names: ``Z`` names (empty for a static model).
        xhat: ``[N, S]`` the model output that goes with ``theta``.
        valid: ``[N]`` bool; False where the sample was skipped (``reason``): its
            row repeats the unit's last used row, or the prior before the first
            (module docstring).
        reason: ``[N]`` str: ``ok`` or why the sample was skipped (the guard's
            :data:`~jaxcal.calibrators.guard.REASONS`, ``outlier`` among them).
        partial: ``[N]`` bool: some outputs of the row were missing (NaN); used on
            the observed outputs where ``valid`` (UKF, LS), else skipped as
            ``x_partial`` (E2E, policy). ``None``: not recorded.
        misfit: ``[N]`` bool: the row's unit has one-step innovations so
            autocorrelated (a model misfit, a drift the filter lags, a quantised
            output) that ``theta_std`` there is not a calibrated uncertainty
            (:mod:`jaxcal.calibrators.uncertainty.misfit_check`). ``None``: not checked
            (no ``theta_std``, or no screening pass to read the innovations from).
        at_bound: ``[N]`` bool: the row's estimate reached a bound of the declared
            box (every method's ``theta`` is kept inside it; the data may call for
            a value beyond it, or the model misfits there). ``None``: not
            recorded.
        theta_names, output_names: column names.
        unit, time: ``[N]`` the rows' unit and time (as read).
        method: the method's name.
        problem: the :class:`~jaxcal.problem.Problem` that was solved.
        notes: what data cleaning did (conditions within 1 % of their range outside
            it, logging jitter, set onto the bound; farther ones are flagged) and
            the console lines: skipped rows per reason, the outliers, the model's
            non-finite outputs, a given noise far narrower than the data.
        stored: the metadata of the file the result was loaded from (units, noise
            source, problem JSON; module docstring), so that a result loaded
            without its model still knows them; ``None`` for a fresh result.
    """

    theta: np.ndarray
    theta_std: np.ndarray | None
    states: np.ndarray | None
    state_names: tuple[str, ...]
    xhat: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    theta_names: tuple[str, ...]
    output_names: tuple[str, ...]
    unit: np.ndarray
    time: np.ndarray
    method: str
    problem: Problem
    notes: tuple[str, ...] = ()
    partial: np.ndarray | None = None
    misfit: np.ndarray | None = None
    at_bound: np.ndarray | None = None
    stored: Mapping | None = dataclasses.field(default=None, repr=False)

    @property
    def noise_source(self) -> str:
        """Where the output noise came from: ``"given"`` or how it was estimated
        (``problem.noise_std`` holds its value)."""
        if self.problem is not None:
            return self.problem.noise_source
        if self.stored and self.stored.get("noise_source") is not None:
            return self.stored["noise_source"]
        raise ValueError(
            "CalibrationResult.noise_source: this result has no problem (load it "
            "with CalibrationResult.load(path, model=...) to restore it)"
        )

    @property
    def noise(self) -> dict[str, float]:
        """``{output: std}``: the measurement noise the calibration used, given or
        estimated (:attr:`noise_source`), in the form ``jaxcal.calibrate(noise=)``
        takes and ``noise=name:std,...`` spells on a command line: to pass on."""
        if self.problem is not None:
            stds = self.problem.noise_std
        elif self.stored and (self.stored.get("problem") or {}).get("noise_std"):
            stds = self.stored["problem"]["noise_std"]
        else:
            raise ValueError(
                "CalibrationResult.noise: this result has no problem (load it with "
                "CalibrationResult.load(path, model=...) to restore it)"
            )
        return {n: float(s) for n, s in zip(self.output_names, stds, strict=True)}

    def variable_units(self) -> dict[str, str]:
        """``{name: unit}`` of the parameters, outputs and states (the model's; for
        a result loaded without its model, the file's; ``{}`` if neither)."""
        names = (*self.theta_names, *self.output_names, *self.state_names)
        if self.problem is None:
            return dict((self.stored or {}).get("units", {}))
        model = self.problem.model
        known = {*model.parameter_names, *model.output_names, *model.state_names}
        return {n: model.unit_of(n) for n in names if n in known}

    @property
    def num_partial(self) -> dict:
        """``{"used": rows, "skipped": rows}`` of the rows with missing outputs."""
        partial = np.zeros_like(self.valid) if self.partial is None else self.partial
        return {
            "used": int(np.sum(partial & self.valid)),
            "skipped": int(np.sum(partial & ~self.valid)),
        }

    @property
    def num_flagged(self) -> dict:
        """``{reason: rows}`` of the skipped rows."""
        names, counts = np.unique(self.reason[~self.valid], return_counts=True)
        return {str(n): int(c) for n, c in zip(names, counts, strict=True)}

    def to_frame(self):
        """A pandas DataFrame: unit, time, theta (and ``<name>_std``), x-hat
        (``<name>_hat``), valid, reason, partial, misfit, at_bound."""
        cols = {"unit": self.unit, "time": self.time}
        for j, name in enumerate(self.theta_names):
            cols[name] = self.theta[:, j]
            if self.theta_std is not None:
                cols[f"{name}_std"] = self.theta_std[:, j]
        if self.states is not None:
            for j, name in enumerate(self.state_names):
                cols[name] = self.states[:, j]
        for j, name in enumerate(self.output_names):
            cols[f"{name}_hat"] = self.xhat[:, j]
        cols["valid"], cols["reason"] = self.valid, self.reason
        if self.partial is not None:
            cols["partial"] = self.partial
        if self.misfit is not None:
            cols["misfit"] = self.misfit
        if self.at_bound is not None:
            cols["at_bound"] = self.at_bound
        return pd.DataFrame(cols)

    # ---------------------------------------------------------------- reading

    def summary(self, max_units: int = 5) -> str:
        """The last estimate of each unit (its latest row in time), ``± std`` where
        the method gives one, and the last hidden state of a model with memory.

        Args:
            max_units: list at most this many units (then how many more there are).

        Returns:
            A few lines of text, the first one the method, rows and skipped rows.
        """
        num_rows, skipped = len(self.valid), int(np.sum(~self.valid))
        units = self.variable_units()
        order = np.lexsort((self.time, self.unit))
        ids = self.unit[order]
        last = order[np.r_[ids[1:] != ids[:-1], True]] if num_rows else order
        lines = [
            f"{self.method}: {num_rows} rows in {len(last)} unit(s), {skipped} skipped"
        ]

        def value(name, v, s=None):
            unit = units.get(name, "-")
            std = "" if s is None else f" ± {s:.2g}"
            return f"{name} = {v:.4g}{std}" + ("" if unit == "-" else f" {unit}")

        no_std = [None] * len(self.theta_names)
        for i in last[:max_units]:
            std = no_std if self.theta_std is None else self.theta_std[i]
            parts = [
                value(n, v, s)
                for n, v, s in zip(self.theta_names, self.theta[i], std, strict=True)
            ]
            line = f"unit {self.unit[i]} at time {self.time[i]:g}: " + ", ".join(parts)
            if self.states is not None and len(self.state_names):
                line += "; state " + ", ".join(
                    value(n, v)
                    for n, v in zip(self.state_names, self.states[i], strict=True)
                )
            lines.append(line)
        if len(last) > max_units:
            lines.append(f"... and {len(last) - max_units} more unit(s)")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()

    def plot(self, units=None, max_units: int = 6):
        """Each parameter against time per unit, its ±2 std band where the method
        gives a std, the skipped rows (``valid`` False) marked.

        Args:
            units: the unit ids to draw (default: the first ``max_units``).
            max_units: how many units to draw when ``units`` is not given.

        Returns:
            A ``matplotlib.figure.Figure`` (no pyplot state; ``fig.savefig(path)``).
        """
        # light --help: matplotlib loads for a figure only (the train and fleet
        # command lines import this module before their arguments are checked)
        from jaxcal.plotting import unit_traces_figure

        known = self.variable_units()
        labels = [
            n if known.get(n, "-") == "-" else f"{n} [{known[n]}]"
            for n in self.theta_names
        ]
        return unit_traces_figure(
            self.time, self.unit, self.theta, self.theta_names,
            theta_std=self.theta_std, valid=self.valid, units=units,
            max_units=max_units, ylabels=labels, title=f"{self.method} estimates",
        )  # fmt: skip

    # ---------------------------------------------------------------- storage

    def _columns(self) -> dict:
        """Each array field's column names in :meth:`to_frame` (``None``: absent)."""
        return {
            "theta": list(self.theta_names),
            "theta_std": None
            if self.theta_std is None
            else [f"{n}_std" for n in self.theta_names],
            "states": None if self.states is None else list(self.state_names),
            "xhat": [f"{n}_hat" for n in self.output_names],
            "unit": "unit",
            "time": "time",
            "valid": "valid",
            "reason": "reason",
            "partial": None if self.partial is None else "partial",
            "misfit": None if self.misfit is None else "misfit",
            "at_bound": None if self.at_bound is None else "at_bound",
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write the result to one Parquet file (module docstring), atomically: a
        temporary file beside ``path``, then renamed over it.

        Args:
            path: the file (``.parquet`` by convention); its folder is created.

        Returns:
            The path.
        """
        check_output_path(os.fspath(path), "path")  # a folder, under a file, ...
        columns = self._columns()
        names = [
            c for v in columns.values() if v for c in ([v] if isinstance(v, str) else v)
        ]
        if len(set(names)) != len(names):  # to_frame would keep only one of them
            raise ValueError(f"CalibrationResult.save: column names collide: {names}")
        frame = self.to_frame()
        stored = dict(self.stored or {})
        meta = {
            "format": "jaxcal.CalibrationResult",
            "version": FORMAT_VERSION,
            "method": self.method,
            "theta_names": list(self.theta_names),
            "output_names": list(self.output_names),
            "state_names": list(self.state_names),
            "units": self.variable_units(),
            "notes": list(self.notes),
            "noise_source": self.problem.noise_source
            if self.problem is not None
            else stored.get("noise_source"),
            "problem": self.problem.to_json()
            if self.problem is not None
            else stored.get("problem"),
            "columns": columns,
            "dtypes": {
                f: None if getattr(self, f) is None else str(getattr(self, f).dtype)
                for f in (*_ARRAYS, *_OPTIONAL)
            },
        }
        table = pa.Table.from_pandas(frame, preserve_index=False)
        table = table.replace_schema_metadata(
            {**(table.schema.metadata or {}), META_KEY: json.dumps(meta).encode()}
        )
        return write_atomic_with(path, lambda f: pq.write_table(table, f))

    @classmethod
    def load(cls, path: str | os.PathLike, model=None) -> CalibrationResult:
        """Read a result written by :meth:`save`.

        Args:
            path: the Parquet file.
            model: the result's model (a :class:`~jaxcal.model.Model` or a
                :func:`jaxcal.models.load` spec) to restore ``problem``; ``None``:
                ``problem`` is ``None`` (the rest is restored).

        Returns:
            The result, every array with its saved dtype.

        Raises:
            ValueError: no such file, not a Parquet file, not a jaxcal result, or
                a ``model`` that is not the result's; the message names the file.
        """
        if not Path(path).is_file():
            what = "not a file" if Path(path).exists() else "no such file"
            raise ValueError(f"{path}: {what}")
        try:
            table = pq.read_table(path)
        except Exception as err:  # pyarrow raises several types for a bad file
            raise ValueError(f"{path}: not a Parquet file ({err})") from err
        raw = (table.schema.metadata or {}).get(META_KEY)
        if raw is None:
            raise ValueError(
                f"{path}: not a jaxcal result file (no {META_KEY.decode()!r} "
                "metadata; CalibrationResult.save writes one)"
            )
        try:
            meta = json.loads(raw)
            if meta.get("format") != "jaxcal.CalibrationResult":
                raise ValueError(f"format {meta.get('format')!r}")
            version = meta["version"]
            fields = {
                f: _read(table, meta["columns"][f], meta["dtypes"][f])
                for f in (*_ARRAYS, "partial")
            }
            # fields added later: absent from the files written before them
            for field in ("misfit", "at_bound"):
                fields[field] = _read(
                    table, meta["columns"].get(field), meta["dtypes"].get(field)
                )
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(
                f"{path}: not a readable jaxcal result file ({err!r})"
            ) from err
        if version > FORMAT_VERSION:
            raise ValueError(
                f"{path}: result format {version} is newer than this jaxcal's "
                f"({FORMAT_VERSION}); update jaxcal to read it"
            )
        _check_stored(meta, path)
        problem = None
        if model is not None:
            problem = _problem(meta, model, path)
        return cls(
            **fields,
            state_names=tuple(meta["state_names"]),
            theta_names=tuple(meta["theta_names"]),
            output_names=tuple(meta["output_names"]),
            method=str(meta["method"]),
            problem=problem,
            notes=tuple(meta["notes"]),
            stored=meta,
        )


# the dtype kinds a stored field may have (a tampered file's dtype is not obeyed)
_KINDS = {"theta": "f", "theta_std": "f", "states": "f", "xhat": "f", "unit": "iu",
          "time": "iuf", "valid": "b", "reason": "UO", "partial": "b",
          "misfit": "b", "at_bound": "b"}  # fmt: skip
_NAMES = {"theta": "theta_names", "states": "state_names", "xhat": "output_names"}


def _check_stored(meta: Mapping, path) -> None:
    """Every stored dtype of the kind its field has, and one column per name:
    a file edited by hand or by a faulty tool is an error naming the field."""
    for field, kinds in _KINDS.items():
        dtype = meta["dtypes"].get(field)
        if dtype is None:
            continue
        try:
            kind = np.dtype(dtype).kind
        except TypeError:
            kind = "?"
        if kind not in kinds:
            raise ValueError(
                f"{path}: field {field!r} is stored with dtype {dtype!r}; a result "
                f"keeps it as {_KIND_WORDS[kinds]}: the file was altered, save the "
                "result again"
            )
    for field, names in _NAMES.items():
        columns = meta["columns"].get(field)
        if columns is not None and len(columns) != len(meta[names]):
            raise ValueError(
                f"{path}: field {field!r} has {len(columns)} columns for the "
                f"{len(meta[names])} {names} {meta[names]}: the file was altered"
            )


_KIND_WORDS = {"f": "floats", "iu": "integers", "iuf": "numbers", "b": "booleans",
               "UO": "strings"}  # fmt: skip


def _read(table, columns, dtype) -> np.ndarray | None:
    """One field from its column(s) (a name or a list, ``None``: absent)."""
    if columns is None:
        return None
    if isinstance(columns, str):
        return np.asarray(table.column(columns).to_numpy(zero_copy_only=False), dtype)
    cols = [table.column(c).to_numpy(zero_copy_only=False) for c in columns]
    if not cols:
        return np.empty((table.num_rows, 0), dtype)
    return np.stack(cols, axis=1).astype(dtype)


def _problem(meta: Mapping, model, path) -> Problem:
    """The saved problem on ``model`` (checked to have the result's variables)."""
    model = load_model(model)
    data = meta.get("problem")
    if data is None:
        raise ValueError(f"{path}: the result was saved without its problem")
    missing = [
        n
        for names, have in (
            (data["theta_names"], model.parameter_names),
            (data["output_names"], model.output_names),
        )
        for n in names
        if n not in have
    ]
    if (
        missing
        or tuple(meta["state_names"]) != model.state_names
        or len(data["theta_base"]) != len(model.parameters)
    ):
        raise ValueError(
            f"{path}: model {model.name!r} is not the result's ({data['model']!r}): "
            f"parameters {list(model.parameter_names)}, outputs "
            f"{list(model.output_names)}, states {list(model.state_names)}"
            + (f"; it lacks {missing}" if missing else "")
        )
    return Problem.from_json(data, model)
