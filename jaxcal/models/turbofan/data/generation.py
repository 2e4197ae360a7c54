"""Generating one of the paper's data sets into a file: a function, not a process.

:func:`generate_dataset` writes the data set of a
:class:`~jaxcal.models.turbofan.data.dataset_configs.DatasetConfig` in the N-CMAPSS HDF5
layout (:func:`jaxcal.models.turbofan.data.builders.build_dataset`: atomically, the
resolved config as the root attribute ``config``), with a progress bar over the
generation blocks. The engine's Newton solve needs float64, and the caller (a training
job) may run in float32: float64 is switched on for the generation only (``with
jax.enable_x64(True)``), so nothing of it leaks into the caller; the engine is loaded
inside that scope, so its design constants take the float64 dtype. ``python -m
jaxcal.generate`` (:mod:`jaxcal.cli.generate`) and the training job's missing data
file (:func:`jaxcal.training.data.run.ensure_data_file`) both call it.
"""

from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING

import jax

from jaxcal.models.turbofan.data.dataset_configs import DATASETS, DatasetConfig
from jaxcal.progress import progress_bar

if TYPE_CHECKING:  # the builders (the engine's solve) load on the first generation
    from jaxcal.models.turbofan.data.builders import BuildSummary


def dataset_preset(name: str) -> DatasetConfig:
    """The data set preset ``name`` of
    :data:`~jaxcal.models.turbofan.data.dataset_configs.DATASETS`.

    Raises:
        ValueError: ``name`` is missing (``None``) or not a preset (the message lists
            the presets).
    """
    if name not in DATASETS:
        got = "missing" if name is None else f"unknown dataset {name!r}"
        raise ValueError(f"{got}: choose dataset= one of {', '.join(DATASETS)}")
    return DATASETS[name]


def generate_dataset(
    cfg: DatasetConfig, out: str | os.PathLike, *, progress: bool = True
) -> BuildSummary:
    """Generate the data set ``cfg`` into the file ``out`` (its folder is created).

    Args:
        cfg: the data set (a preset of :func:`dataset_preset`, fields overridden
            as wished).
        out: the ``.h5`` file to write, atomically.
        progress: show a tqdm bar over the generation blocks on stderr.

    Returns:
        :class:`~jaxcal.models.turbofan.data.builders.BuildSummary` (rows and units per
        split).

    Raises:
        ValueError: engine samples that do not converge
            (:func:`~jaxcal.models.turbofan.data.builders.build_dataset`).
    """
    # light --help: the engine and the file writers load when a data set is made
    # (python -m jaxcal.generate imports this module before its arguments are checked)
    from jaxcal.models.turbofan.data.builders import build_dataset

    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    bar = progress_bar(
        unit="block", desc="solving reference", dynamic_ncols=True,
        disable=not progress,
    )  # fmt: skip
    with jax.enable_x64(True), bar:

        def on_block(done: int, total: int, rows: int) -> None:
            if bar.total != total:
                bar.total = total
                bar.set_description(cfg.name)
            bar.update(done - bar.n)
            bar.set_postfix(rows=f"{rows:,}", refresh=False)

        return build_dataset(cfg, out, on_block=on_block)


def summary_line(summary: BuildSummary, out: str | os.PathLike, start: float) -> str:
    """What a generation wrote, its size and speed, as one line (``start``: its
    ``time.perf_counter()`` at the start)."""
    wall = time.perf_counter() - start
    rows = sum(summary.rows.values())
    size_mb = os.path.getsize(out) / 1e6
    return (
        f"wrote {rows:,} rows (dev {summary.rows['dev']:,}, test "
        f"{summary.rows['test']:,}; re-solved {summary.num_retried:,}) to {out} "
        f"({size_mb:,.1f} MB) in {wall:,.1f} s: {rows / wall:,.0f} samples/s"
    )
