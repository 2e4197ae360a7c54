"""The turbofan's data of a training run: an N-CMAPSS-layout file, or generated.

:class:`~jaxcal.training.data.calibration.CalibrationData` is what training,
evaluation and the paper's comparison read: the train / validation / test units as
:class:`~jaxcal.data.padded.Padded` and the problem they define
(:mod:`jaxcal.training.data.calibration`). Two sources make one:

* :func:`load_calibration_data` (this module) reads an N-CMAPSS-layout HDF5 file (one
  of ours or any of NASA's DS01-DS08) for the turbofan (:func:`read_data`: a
  training run's, named by :data:`jaxcal.models.TRAINING_FILES`, as
  :func:`generator` makes a missing file);
* :func:`jaxcal.training.data.tables.load_table_data` reads any model's rows (CSV,
  Parquet, C-MAPSS text) through :func:`jaxcal.data.readers.read_dataset`.

Each unit is padded to the longest one of its split (the padding repeats the unit's
last row, :meth:`jaxcal.data.dataset.Dataset.padded`) with its valid length. Only
the needed columns and the rows of the needed units of an HDF5 file are read (the
N-CMAPSS reader slices by unit,
:func:`jaxcal.models.turbofan.data.datasets.read_ncmapss_split`).

Splits (the policy never sees theta; labels are kept for reporting only):

* train: dev units minus the validation units; the surrogate D and the policy learn on
  them;
* val: held-out dev units (default: the last ``val_fraction`` of the file's dev units),
  used for progress printing and hyperparameter tuning;
* test: the file's test units, scored once at the end.

Defaults follow the file: sensors = the ``observed_sensors`` root attribute when the
file has one (our files), else the 14 measured sensors X_s; theta = the T columns that
vary over the dev split. The action box is the dev range of theta widened by
``theta_margin`` of its width on each side.

Bad input is refused, not repaired in silence: column names the layout does not know
are an error unless ``rename`` maps them, and rows with NaN / Inf are an error naming
the file, columns, first rows and counts unless ``nonfinite="drop"`` (then the drop is
logged and recorded in ``info["dropped"]``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.data.padded import Padded
from jaxcal.model import Model
from jaxcal.models import available, load
from jaxcal.models.turbofan.data.datasets import read_ncmapss_split
from jaxcal.models.turbofan.data.generation import (
    dataset_preset,
    generate_dataset,
    summary_line,
)
from jaxcal.models.turbofan.data.ncmapss_io import ncmapss_info
from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES, MEASURED_SENSOR_NAMES
from jaxcal.precision import float_dtype
from jaxcal.problem import VARYING_TOLERANCE, labelled_box
from jaxcal.training.config import TrainConfig
from jaxcal.training.data.calibration import CalibrationData, training_problem
from jaxcal.training.data.run import read_options, run_dtype


def _json_attr(attrs: dict, key: str):
    value = attrs.get(key)
    if isinstance(value, str):
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    return value


def default_sensors(info: dict) -> tuple[str, ...]:
    """The file's ``observed_sensors`` attribute, else the 14 measured sensors X_s."""
    observed = _json_attr(info["attrs"], "observed_sensors")
    if isinstance(observed, list) and observed:
        return tuple(str(s) for s in observed)
    return tuple(n for n in info["columns"]["X_s"] if n in MEASURED_SENSOR_NAMES)


def split_units(
    info: dict, val_units: tuple[int, ...] | None, val_fraction: float
) -> tuple[list[int], list[int], list[int]]:
    """(train, val, test) unit ids: dev minus val, the chosen val, the test split.

    Args:
        info: :func:`~jaxcal.models.turbofan.data.ncmapss_io.ncmapss_info` of the file.
        val_units: explicit held-out dev units; ``None`` takes the last
            ``max(1, round(val_fraction * n_dev))`` dev units (none if that would
            leave no training unit); ``()`` holds out nothing.
        val_fraction: share of dev units held out when ``val_units`` is ``None``.

    Raises:
        ValueError: a split is missing, a val unit is not a dev unit, or no training
            unit is left.
    """
    splits = info["splits"]
    for split in ("dev", "test"):
        if split not in splits or not splits[split]["units"]:
            raise ValueError(f"{info['path']}: the {split} split holds no unit")
    dev = [int(u) for u in splits["dev"]["units"]]
    test = [int(u) for u in splits["test"]["units"]]
    if val_units is None:
        num_val = max(1, int(round(val_fraction * len(dev)))) if val_fraction else 0
        val = dev[len(dev) - num_val :] if num_val < len(dev) else []
    else:
        val = [int(u) for u in val_units]
        stray = sorted(set(val) - set(dev))
        if stray:
            raise ValueError(
                f"val_units {stray} are not dev units of {info['path']}; dev units: "
                f"{dev}"
            )
    train = [u for u in dev if u not in val]
    if not train:
        raise ValueError(f"val_units {val} leave no training unit (dev units: {dev})")
    return train, val, test


def describe_dropped(dropped: dict) -> str:
    """One line per split of ``info["dropped"]``: rows dropped and per column."""
    return "; ".join(
        f"{split}: {d['rows']} rows with NaN / Inf dropped ("
        + ", ".join(f"{k} {v}" for k, v in d["columns"].items())
        + ")"
        for split, d in dropped.items()
        if d["rows"]
    )


def _pad(data: Dataset, theta_idx: list[int]) -> Padded:
    """A split's units padded in the run's float dtype, in ascending id order (a
    file's order), ``theta`` the declared parameters' columns."""
    by_unit = data.take(np.argsort(data.unit, kind="stable"))
    padded = by_unit.padded(float_dtype())
    # rows index the sorted copy, not the file: not carried
    return padded._replace(theta=padded.theta[..., theta_idx], rows=None)


def load_calibration_data(
    path: str,
    *,
    sensors: tuple[str, ...] = (),
    theta: tuple[str, ...] = (),
    val_units: tuple[int, ...] | None = None,
    val_fraction: float = 0.15,
    stride: int = 1,
    theta_margin: float = 0.1,
    nonfinite: str = "error",
    rename: dict[str, str] | None = None,
    log: Callable[[str], None] | None = None,
    model: Model | None = None,
    norm_dtype=np.float64,
) -> CalibrationData:
    """Reads the train / val / test splits of an N-CMAPSS file.

    Args:
        path: the ``.h5`` file (N-CMAPSS layout).
        sensors: sensor names (``()``: :func:`default_sensors`).
        theta: declared parameter names from ``HEALTH_NAMES`` (``()``: the T columns
            that vary over the dev split).
        val_units: see :func:`split_units`.
        val_fraction: see :func:`split_units`.
        stride: keep every ``stride``-th row (a 1 Hz NASA file with ``stride=10`` is
            sampled every 10 s).
        theta_margin: the action box is the dev range widened by this share of its
            width on each side.
        nonfinite: rows with NaN / Inf in w, the sensors or theta: ``"error"``
            refuses the file, ``"drop"`` drops them (``info["dropped"]``, logged).
        rename: ``{file column name: jaxcal name}`` (see
            :func:`~jaxcal.models.turbofan.data.ncmapss_io.load_ncmapss`).
        log: where the dropped-row summary goes (``None``: not printed).
        model: the turbofan model (``None``: the engine the file names,
            :func:`file_model`).
        norm_dtype: the dtype the problem's normalisation is computed in (a
            training run's: :func:`jaxcal.training.data.run.run_dtype`;
            :func:`~jaxcal.training.data.calibration.training_norm`).

    Returns:
        :class:`CalibrationData`.

    Raises:
        ValueError: naming the bad argument (unknown sensor or parameter, no varying
            parameter, bad split), an unknown or missing column name, or (with
            ``nonfinite="error"``) a NaN / Inf value.
    """
    if theta_margin < 0:
        raise ValueError(f"theta_margin must be >= 0, got {theta_margin}")
    if nonfinite not in ("error", "drop"):
        raise ValueError(f"nonfinite must be 'error' or 'drop', got {nonfinite!r}")
    info = ncmapss_info(path, rename=rename)
    sensors = tuple(sensors) or default_sensors(info)
    train_ids, val_ids, test_ids = split_units(info, val_units, val_fraction)
    read = dict(
        label=False, sensors=sensors, stride=stride, rename=rename, nonfinite=nonfinite
    )
    dev = read_ncmapss_split(path, "dev", units=train_ids + val_ids, **read)
    test = read_ncmapss_split(path, "test", units=test_ids, **read)
    dropped = _dropped_rows(path, dev, test, train_ids + val_ids, test_ids, log)
    theta_names = _theta_names(path, theta, dev)
    theta_idx = [HEALTH_NAMES.index(n) for n in theta_names]
    theta_low, theta_high = labelled_box(dev.theta[:, theta_idx], theta_margin)
    dev_fleet = _pad(dev, theta_idx)
    is_val = np.isin(dev_fleet.unit_ids, val_ids)
    model = file_model(info) if model is None else model
    train = _take(dev_fleet, ~is_val)
    problem = training_problem(
        model, train, theta_names, sensors, dev.theta.mean(axis=0), theta_low,
        theta_high, norm_dtype,
    )  # fmt: skip
    units = {"train": train_ids, "val": val_ids, "test": test_ids}
    return CalibrationData(
        train=train,
        val=_take(dev_fleet, is_val) if val_ids else None,
        test=_pad(test, theta_idx),
        problem=problem,
        info=_provenance(path, info, stride, dev, test, units, dropped),
    )


def _dropped_rows(path, dev: Dataset, test: Dataset, dev_ids, test_ids, log) -> dict:
    """``info["dropped"]``: the rows with NaN / Inf dropped per split and column
    (``nonfinite="drop"``; logged when any).

    Raises:
        ValueError: a unit of ``dev_ids`` / ``test_ids`` lost every row.
    """
    dropped = {
        split: {"rows": rec.dropped_rows, "columns": rec.dropped}
        for split, rec in (("dev", dev), ("test", test))
    }
    if log is not None and (dev.dropped_rows or test.dropped_rows):
        log(f"data {path}: {describe_dropped(dropped)} (dataset.nonfinite=drop)")
    for split, rec, ids in (("dev", dev, dev_ids), ("test", test, test_ids)):
        lost = sorted(set(ids) - set(rec.units.tolist())) if rec.dropped_rows else []
        if lost:
            raise ValueError(
                f"{path}: no {split} row of unit(s) {lost} is left after dropping the "
                "rows with NaN / Inf values; fix the file or leave those units out"
            )
    return dropped


def _theta_names(path, theta: tuple[str, ...], dev: Dataset) -> tuple[str, ...]:
    """The declared parameters: ``theta`` checked against ``HEALTH_NAMES``, or (``()``)
    those that vary over the dev split.

    Raises:
        ValueError: an unknown or repeated name, or no parameter varies.
    """
    low, high = dev.theta.min(axis=0), dev.theta.max(axis=0)
    if theta:
        unknown = [n for n in theta if n not in HEALTH_NAMES]
        if unknown or len(set(theta)) < len(theta):
            raise ValueError(
                f"theta must be distinct names from {list(HEALTH_NAMES)}, got "
                f"{list(theta)}"
            )
        return tuple(theta)
    varying = high - low > VARYING_TOLERANCE
    theta_names = tuple(n for n, v in zip(HEALTH_NAMES, varying, strict=True) if v)
    if not theta_names:
        raise ValueError(
            f"{path}: no health parameter varies over the dev split; name the "
            "parameters to calibrate with theta=<name>,<name>"
        )
    return theta_names


def _take(fleet: Padded, mask: np.ndarray) -> Padded:
    """The units of ``fleet`` where ``mask``, the padding re-trimmed to the longest
    selected unit."""
    longest = int(fleet.lengths[mask].max())
    return Padded(
        *(a[mask][:, :longest] for a in fleet[:3]),
        lengths=fleet.lengths[mask],
        unit_ids=fleet.unit_ids[mask],
    )


def file_model(info: dict) -> Model:
    """The turbofan the file (its
    :func:`~jaxcal.models.turbofan.data.ncmapss_io.ncmapss_info`) names (its ``engine``
    attribute), else ``cmapss``; only a registered name: a data file never names code to
    run (``docs/trust.md``)."""
    engine = _json_attr(info["attrs"], "engine")
    name = str(engine) if engine else "cmapss"
    if name not in available():
        raise ValueError(
            f"the data file's 'engine' attribute names the model {name!r}, not a "
            f"registered model ({', '.join(available())}): a data file never names "
            "code to run; give the model yourself (model=)"
        )
    return load(name)


def _provenance(path, info: dict, stride: int, dev, test, units, dropped) -> dict:
    """``CalibrationData.info``: the file, its sample rate after ``stride``, the rows
    and units per split, the dropped rows."""
    return {
        "path": str(path),
        "sample_rate_hz": info["sample_rate_hz"] / stride,
        "stride": stride,
        "rows": {"dev": dev.num_rows, "test": test.num_rows},
        "units": units,
        "dropped": dropped,
    }


def read_data(cfg: TrainConfig, path: str, *, units: dict, log, model):
    """A training run's data (:func:`jaxcal.training.data.run.read_run_data`: the
    arguments) when ``path`` is an N-CMAPSS file and ``model`` a turbofan (one that
    wraps its engine) or ``None`` (:func:`file_model`); else ``None``: a table."""
    is_h5 = Path(path).suffix.lower() in (".h5", ".hdf5")
    if not is_h5 or (model is not None and model.native is None):
        return None
    options = read_options(cfg.dataset)
    model = model or file_model(ncmapss_info(path, rename=options["rename"]))
    return load_calibration_data(
        path, sensors=cfg.sensors, theta=cfg.theta,
        val_units=units.get("val", cfg.dataset.val_units),
        val_fraction=cfg.dataset.val_fraction, stride=cfg.dataset.stride,
        theta_margin=cfg.env.theta_margin, log=log,  # rows dropped: nonfinite=drop
        model=model, norm_dtype=run_dtype(cfg, model), **options,
    )  # fmt: skip


def generator(name: str) -> Callable[[Path, bool], str]:
    """``generate(path, progress)``: writes the data-set preset ``name``
    (:data:`~jaxcal.models.turbofan.data.dataset_configs.DATASETS`; a bad name: a
    ValueError now) and returns its summary line."""
    preset = dataset_preset(name)

    def generate(path: Path, progress: bool) -> str:
        start = time.perf_counter()
        summary = generate_dataset(preset, path, progress=progress)
        return summary_line(summary, path, start)

    return generate
