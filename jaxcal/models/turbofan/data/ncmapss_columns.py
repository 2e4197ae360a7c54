"""The column names of an N-CMAPSS file, checked against the layout.

Column names are checked, never guessed: every ``*_var`` group must hold exactly the
names of the layout (:data:`~jaxcal.models.turbofan.data.ncmapss_layout.LAYOUT_NAMES`,
any order; X_s / X_v may also hold other jaxcal sensor names), so a renamed sensor
(``T_24`` for ``T24``) is an error that lists what was expected and what was found,
unless the caller maps it with ``rename={"T_24": "T24"}``
(:func:`~jaxcal.data.table_checks.parse_rename` reads the command-line form).
:func:`split_layout` checks a split's datasets against the names.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import h5py
import numpy as np

from jaxcal.models.turbofan.data.ncmapss_layout import (
    _GROUPS,
    LAYOUT_NAMES,
    SPLITS,
    _check_split,
)
from jaxcal.models.turbofan.physics.constants import SENSOR_NAMES


def open_read(path) -> tuple[str, h5py.File]:
    """``(path as str, the open file)``; a missing or non-HDF5 file is a clear error."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"N-CMAPSS file not found: {path}")
    try:
        return path, h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"{path} is not a readable HDF5 file: {err}") from err


def _dataset(f: h5py.File, path: str, key: str) -> h5py.Dataset:
    if key not in f:
        raise ValueError(
            f"{path}: missing dataset {key!r}; an N-CMAPSS file holds "
            f"{[f'{g}_{s}' for s in SPLITS for g in _GROUPS]} and "
            f"{[f'{g}_var' for g in LAYOUT_NAMES]}"
        )
    return f[key]


def _var_names(f: h5py.File, path: str, group: str) -> list[str]:
    """Decoded ``<group>_var`` column names (fixed-width bytes in the real files)."""
    raw = np.asarray(_dataset(f, path, f"{group}_var")[()]).ravel()
    return [
        (v.decode("ascii") if isinstance(v, bytes) else str(v)).strip() for v in raw
    ]


def _check_rename(rename, raw: dict, path: str) -> dict[str, str]:
    """``rename`` as a ``{file name: jaxcal name}`` dict of names the file holds."""
    if rename is None:
        return {}
    if not isinstance(rename, Mapping) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in rename.items()
    ):
        raise ValueError(
            f"rename must map file column names to jaxcal names (str -> str), got "
            f"{rename!r}"
        )
    found = {n for names in raw.values() for n in names}
    stray = sorted(k for k in rename if k not in found)
    if stray:
        raise ValueError(
            f"{path}: rename names column(s) {stray} that no *_var array holds; "
            f"found {dict(raw)}"
        )
    return dict(rename)


def _layout_problems(group: str, names: list[str]) -> str:
    """What is wrong with the (renamed) names of ``<group>_var``; "" when nothing."""
    expected = LAYOUT_NAMES[group]
    # X_s / X_v may carry any sensor jaxcal knows (e.g. the C-MAPSS extras epr, BPR).
    allowed = SENSOR_NAMES if group in ("X_s", "X_v") else expected
    unknown = [n for n in names if n not in allowed]
    missing = [n for n in expected if n not in names]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if not (unknown or missing or repeated):
        return ""
    what = [
        f"{label} {items}"
        for label, items in (
            ("unknown", unknown),
            ("missing", missing),
            ("repeated", repeated),
        )
        if items
    ]
    return (
        f"{group}_var: {', '.join(what)}; expected (any order) {list(expected)}, "
        f"found {names}"
    )


def column_names(f: h5py.File, path: str, rename=None) -> dict[str, list[str]]:
    """The checked column names of every group, after ``rename``.

    Raises:
        ValueError: a name is unknown, missing or repeated in its group, or a sensor
            is in both X_s and X_v; the message lists, per group, what was expected
            and what was found, and how to map names.
    """
    raw = {g: _var_names(f, path, g) for g in LAYOUT_NAMES}
    mapping = _check_rename(rename, raw, path)
    names = {g: [mapping.get(n, n) for n in raw[g]] for g in LAYOUT_NAMES}
    problems = [p for g in LAYOUT_NAMES if (p := _layout_problems(g, names[g]))]
    both = sorted(set(names["X_s"]) & set(names["X_v"]))
    if both:
        problems.append(f"sensor(s) {both} in both X_s_var and X_v_var")
    if problems:
        raise ValueError(
            f"{path}: column names do not match the N-CMAPSS layout: "
            + "; ".join(problems)
            + ". Map other names with rename={'<file name>': '<jaxcal name>'} "
            "(train / evaluate: dataset.rename=<file name>:<jaxcal name>,...)"
        )
    return names


def split_layout(f: h5py.File, path: str, split: str, names: dict) -> dict:
    """Datasets of ``split``, with their shapes checked against ``names``."""
    _check_split(split)
    dsets = {g: _dataset(f, path, f"{g}_{split}") for g in _GROUPS}
    num_rows = dsets["A"].shape[0]
    for group, dset in dsets.items():
        k = 1 if group == "Y" else len(names[group])
        if dset.ndim != 2 or dset.shape != (num_rows, k):
            raise ValueError(
                f"{path}: dataset {group}_{split} has shape {dset.shape}, expected "
                f"({num_rows}, {k}) from A_{split} and {group}_var"
            )
    return {"dsets": dsets, "names": names, "num_rows": num_rows}
