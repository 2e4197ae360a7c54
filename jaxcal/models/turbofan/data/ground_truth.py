"""Per-engine facts of the real N-CMAPSS data set, as loader, statistics and constants.

This module owns what the generators know about real degradation: the end-of-life (EOL)
change of each health modifier, the abnormal-onset cycle ``t_s`` and the EOL cycle per
flight class. The numbers come from ``fault_ground_truth.csv`` (one row per engine of
DS01..DS08c, 99 engines), derived from the real N-CMAPSS arrays by github.com/Ladams537/
predictive-maintenance (``reports/ncmapss/fault_ground_truth.csv`` @ eaa7488f; a copy
lives in the shared data folder, see data_facts.md sections 3 and 4).

The generator defaults are the module constants below, copied from
:func:`summarize_ground_truth` run on that file, so that nothing in the library or the
tests needs the file itself. :func:`load_fault_ground_truth` is host-side (csv + numpy)
and lets a user recompute the statistics, e.g. for one subset or one failure mode.
"""

from __future__ import annotations

import csv
import os
from typing import NamedTuple

import numpy as np

from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES

FLIGHT_CLASSES: tuple[int, ...] = (1, 2, 3)

# Abnormal onset t_s (first cycle with hs = 0), min / max per flight class over all 99
# engines of the CSV (medians 36 / 23 / 17): longer flights reach onset in fewer cycles.
ONSET_CYCLES_BY_CLASS: tuple[tuple[int, int], ...] = ((28, 38), (19, 26), (15, 19))
ONSET_MEDIAN_BY_CLASS: tuple[float, ...] = (36.0, 23.0, 17.0)

# End-of-life cycle, min / max per flight class, all 99 engines (medians 85 / 71 / 69).
EOL_CYCLES_BY_CLASS: tuple[tuple[int, int], ...] = ((72, 100), (54, 100), (48, 100))
EOL_MEDIAN_BY_CLASS: tuple[float, ...] = (85.0, 71.0, 69.0)

# EOL change of each modifier (most negative, least negative) over the engines in which
# that modifier moves at all (all subsets of the CSV).
EOL_DELTA_RANGE: dict[str, tuple[float, float]] = {
    "fan_eff_mod": (-0.22331, -0.00178),
    "fan_flow_mod": (-0.12042, -0.00333),
    "LPC_eff_mod": (-0.13321, -0.00175),
    "LPC_flow_mod": (-0.1547, -0.00327),
    "HPC_eff_mod": (-0.02508, -0.00197),
    "HPC_flow_mod": (-0.07784, -0.00327),
    "HPT_eff_mod": (-0.01851, -0.00143),
    "HPT_flow_mod": (-0.03843, -0.00358),
    "LPT_eff_mod": (-0.03602, -0.00149),
    "LPT_flow_mod": (-0.03884, -0.00353),
}

# Generator defaults for the EOL value of a degrading modifier. HPT_eff uses its
# single-fault range (the 13 HPT-only engines of DS01/DS02: -0.01851 ... -0.0065,
# rounded out to -0.019 as in datasets.md), because the paper's Dataset #1 is an
# HPT_eff-only fleet; the other modifiers use the all-engine range above.
DEFAULT_EOL_THETA_RANGE: dict[str, tuple[float, float]] = {
    **EOL_DELTA_RANGE,
    "HPT_eff_mod": (-0.019, -0.0065),
}

_REQUIRED_COLUMNS = (
    "subset",
    "split",
    "unit",
    "flight_class",
    "eol_cycle",
    "abnormal_from_cycle",
    "components",
) + tuple(f"delta_{name}" for name in HEALTH_NAMES)


class FaultGroundTruth(NamedTuple):
    """One row per engine of ``fault_ground_truth.csv`` (``E`` engines), in numpy."""

    subset: np.ndarray  # [E] str, e.g. "DS01-005"
    split: np.ndarray  # [E] str, "dev" or "test"
    unit: np.ndarray  # [E] int
    flight_class: np.ndarray  # [E] int in {1, 2, 3}
    eol_cycle: np.ndarray  # [E] int, last cycle (RUL 0)
    onset_cycle: np.ndarray  # [E] int, t_s = first cycle with hs = 0
    components: np.ndarray  # [E] str, e.g. "HPT+LPT"
    delta: np.ndarray  # [E, 10] float, EOL minus first-cycle value, HEALTH_NAMES order


class GroundTruthStats(NamedTuple):
    """Statistics that set generator defaults.

    ``eol_delta_range`` / ``eol_delta_median`` hold only the modifiers that move in at
    least one selected engine. The per-class dicts map a flight class to (min, median,
    max) and hold only the classes present.
    """

    num_engines: int
    eol_delta_range: dict[str, tuple[float, float]]
    eol_delta_median: dict[str, float]
    onset_by_class: dict[int, tuple[float, float, float]]
    eol_by_class: dict[int, tuple[float, float, float]]


def load_fault_ground_truth(path: str | os.PathLike) -> FaultGroundTruth:
    """Read ``fault_ground_truth.csv`` (host-side).

    Args:
        path: the CSV file.

    Returns:
        The engines as :class:`FaultGroundTruth`.

    Raises:
        FileNotFoundError: the file does not exist (the message names the path).
        ValueError: a required column is missing, or a number cannot be parsed.
    """
    if not os.path.isfile(path):
        raise FileNotFoundError(
            f"fault ground-truth CSV not found: {os.fspath(path)!r}"
        )
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in _REQUIRED_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{os.fspath(path)!r}: missing column(s) {missing}")
        rows = list(reader)
    try:
        return FaultGroundTruth(
            subset=np.array([r["subset"] for r in rows], dtype=str),
            split=np.array([r["split"] for r in rows], dtype=str),
            unit=np.array([int(r["unit"]) for r in rows], dtype=np.int64),
            flight_class=np.array(
                [int(r["flight_class"]) for r in rows], dtype=np.int64
            ),
            eol_cycle=np.array([int(r["eol_cycle"]) for r in rows], dtype=np.int64),
            onset_cycle=np.array(
                [int(r["abnormal_from_cycle"]) for r in rows], dtype=np.int64
            ),
            components=np.array([r["components"] for r in rows], dtype=str),
            delta=np.array(
                [[float(r[f"delta_{n}"]) for n in HEALTH_NAMES] for r in rows],
                dtype=np.float64,
            ).reshape(len(rows), len(HEALTH_NAMES)),
        )
    except ValueError as err:
        raise ValueError(f"{os.fspath(path)!r}: unparsable value ({err})") from err


def summarize_ground_truth(
    gt: FaultGroundTruth,
    *,
    subsets: tuple[str, ...] | None = None,
    components: tuple[str, ...] | None = None,
) -> GroundTruthStats:
    """Per-parameter EOL magnitudes and per-class onset / EOL cycles.

    Args:
        gt: engines from :func:`load_fault_ground_truth`.
        subsets: keep only these subsets (e.g. ``("DS01-005",)``); None keeps all.
        components: keep only these failure modes (e.g. ``("HPT",)``); None keeps all.

    Returns:
        :class:`GroundTruthStats` of the selected engines.

    Raises:
        ValueError: the selection is empty.
    """
    keep = np.ones(gt.unit.shape, dtype=bool)
    if subsets is not None:
        keep &= np.isin(gt.subset, list(subsets))
    if components is not None:
        keep &= np.isin(gt.components, list(components))
    if not keep.any():
        raise ValueError(
            f"no engine matches subsets={subsets} components={components}; "
            f"subsets present: {sorted(set(gt.subset))}, "
            f"failure modes present: {sorted(set(gt.components))}"
        )
    delta = gt.delta[keep]
    delta_range, delta_median = {}, {}
    for j, name in enumerate(HEALTH_NAMES):
        moved = delta[:, j][delta[:, j] != 0.0]
        if moved.size:
            delta_range[name] = (float(moved.min()), float(moved.max()))
            delta_median[name] = float(np.median(moved))

    def per_class(values: np.ndarray) -> dict[int, tuple[float, float, float]]:
        classes = gt.flight_class[keep]
        return {
            int(c): (
                float(values[classes == c].min()),
                float(np.median(values[classes == c])),
                float(values[classes == c].max()),
            )
            for c in np.unique(classes)
        }

    return GroundTruthStats(
        num_engines=int(keep.sum()),
        eol_delta_range=delta_range,
        eol_delta_median=delta_median,
        onset_by_class=per_class(gt.onset_cycle[keep]),
        eol_by_class=per_class(gt.eol_cycle[keep]),
    )
