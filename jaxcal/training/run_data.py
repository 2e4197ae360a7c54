"""Which data a training run reads: its file (generated when missing) and its splits.

:func:`ensure_data_file` makes sure the run's data file exists (``python -m
jaxcal.generate`` in a subprocess, so the engine's float64 setting does not leak into
training) and is readable; :func:`read_run_data` reads the train / val / test units
and the one :class:`~jaxcal.problem.Problem` (an N-CMAPSS file through
:mod:`jaxcal.training.data`, any model's rows through :mod:`jaxcal.training.tables`);
:func:`model_spec` is the model spec a run folder stores. Nothing here writes to the
run folder: :func:`jaxcal.training.pipeline.run_training` calls these before it
creates one.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import h5py

from jaxcal.config import TrainConfig
from jaxcal.model import Model
from jaxcal.settings import check_output_path
from jaxcal.training.data import (
    CalibrationData,
    load_calibration_data,
    read_options,
)


class GenerationError(RuntimeError):
    """The data generator subprocess failed for another reason than bad arguments."""


def ensure_data_file(cfg: TrainConfig, log: Callable[[str], None] = print) -> Path:
    """The run's data file, generated first if missing and ``dataset.generate`` is set.

    Raises:
        ValueError: no path configured (``dataset=ncmapss`` without ``path=``), an
            unreadable file, a path the generator could not write or bad generator
            arguments.
        FileNotFoundError: the file is missing and no generator preset is named.
        GenerationError: the generator failed otherwise.
    """
    if not cfg.dataset.path:
        raise ValueError(
            f"dataset={cfg.dataset.name} needs a file: add path=<file.h5> "
            "(an N-CMAPSS DS01-DS08 file or one written by jaxcal.generate)"
        )
    path = Path(cfg.dataset.path)
    if path.is_file():
        return _check_readable(path)
    if not cfg.dataset.generate:
        raise FileNotFoundError(f"data file {path} not found")
    check_output_path(str(path), "dataset.path")  # before minutes of generation
    log(f"{path} is missing: generating data set {cfg.dataset.generate!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    command = [
        sys.executable,
        "-m",
        "jaxcal.generate",
        f"dataset={cfg.dataset.generate}",
        f"out={path}",
    ]
    code = subprocess.run(command, check=False).returncode
    if code == 2:  # the generator's code for bad arguments (it printed why)
        raise ValueError(f"generating {path}: bad arguments: {' '.join(command)}")
    if code != 0:
        raise GenerationError(f"generating {path} failed: {' '.join(command)}")
    return path


def _check_readable(path: Path) -> Path:
    """``path``, or a ``ValueError`` naming it when it cannot be opened or, named
    ``.h5``/``.hdf5``, is not an HDF5 file (the reader's own error names neither)."""
    try:
        with open(path, "rb"):
            pass
    except OSError as err:
        raise ValueError(f"dataset.path={str(path)!r}: cannot read ({err})") from None
    if path.suffix.lower() in (".h5", ".hdf5") and not h5py.is_hdf5(path):
        raise ValueError(
            f"dataset.path={str(path)!r}: not an HDF5 file (expected the N-CMAPSS "
            "layout, as NASA's DS01-DS08 files or one written by jaxcal.generate)"
        )
    return path


def model_spec(cfg: TrainConfig, model: Model) -> str:
    """The ``jaxcal.models.load`` spec a run folder stores: ``cfg.model`` (a file
    path made absolute, so the run loads from any folder) or the model's name."""
    spec = cfg.model or model.name
    where, sep, attr = spec.rpartition(":")
    if sep and (where.endswith(".py") or os.sep in where):
        spec = f"{os.path.abspath(where)}:{attr}"
    return spec


def read_run_data(
    cfg: TrainConfig,
    *,
    path: str | os.PathLike | None = None,
    units: dict | None = None,
    log: Callable[[str], None] | None = None,
    model: Model | None = None,
) -> CalibrationData:
    """The splits and problem of ``cfg``'s data (no writes).

    Args:
        cfg: the run's config (``model``, ``dataset``, ``sensors``, ``theta``).
        path: the data file (default ``cfg.dataset.path``).
        units: ``{"val": [...], "test": [...]}`` to reproduce a run's split
            (``data.json``); ``None``: the config's.
        log: where reader notes go.
        model: the model (default: ``jaxcal.models.load(cfg.model)``; a run's own
            when its data are read again).

    Raises:
        ValueError: a bad ``model=`` spec, a table without ``model=``, or bad data.
    """
    from jaxcal.models import load

    path = str(path or cfg.dataset.path)
    if model is None and cfg.model:
        model = load(cfg.model)
    units = units or {}
    is_h5 = Path(path).suffix.lower() in (".h5", ".hdf5")
    if is_h5 and (model is None or model.native is not None):
        return load_calibration_data(
            path,
            sensors=cfg.sensors,
            theta=cfg.theta,
            val_units=units.get("val", cfg.dataset.val_units),
            val_fraction=cfg.dataset.val_fraction,
            stride=cfg.dataset.stride,
            theta_margin=cfg.env.theta_margin,
            log=log,  # rows dropped by dataset.nonfinite=drop
            model=model,
            **read_options(cfg.dataset),
        )
    if model is None:
        raise ValueError(
            f"data={path}: name the model its columns follow with model=<name | "
            "module:attr | path.py:attr>"
        )
    from jaxcal.training.tables import load_table_data

    return load_table_data(
        path,
        model,
        theta=cfg.theta,
        outputs=cfg.sensors,
        test_units=units.get("test", cfg.dataset.test_units),
        val_units=units.get("val", cfg.dataset.val_units),
        test_fraction=cfg.dataset.test_fraction,
        val_fraction=cfg.dataset.val_fraction,
        theta_margin=cfg.env.theta_margin,
        use_labels=cfg.dataset.labels == "use",
        **read_options(cfg.dataset),
    )
