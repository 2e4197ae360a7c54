"""Scoring predicted RULs against the truth: RMSE, the PHM08 score, interval coverage.

The PHM08 score (Saxena et al., *Damage propagation modeling for aircraft engine
run-to-failure simulation*, PHM 2008, eq. 1) penalises late predictions more than early
ones: ``sum(exp(-d / 13) - 1)`` for ``d = predicted - true < 0`` and ``exp(d / 10) - 1``
for ``d >= 0``. Truth files are NASA's ``RUL_FD00x.txt`` (one integer per test unit,
in unit order) or any one-number-per-line text.
"""

from __future__ import annotations

import numpy as np


def phm08_score(error: np.ndarray) -> float:
    """The PHM08 asymmetric score of ``error = predicted - true`` (lower is better)."""
    d = np.asarray(error, np.float64)
    return float(np.sum(np.where(d < 0, np.expm1(-d / 13.0), np.expm1(d / 10.0))))


def crps(samples: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``[U]`` the continuous ranked probability score of each unit's RUL samples
    ``[U, K]`` against its truth (Gneiting & Raftery, JASA 102, 2007, eq. 21:
    ``E|X - y| - E|X - X'| / 2``; lower is better). A proper score: it rewards a
    distribution both calibrated and sharp, so choices made by it keep intervals
    honest without widening them for safety."""
    x = np.sort(np.asarray(samples, np.float64), axis=1)
    k = x.shape[1]
    spread = (x * (2 * np.arange(1, k + 1) - k - 1)).sum(1) / k**2  # E|X - X'| / 2
    return np.abs(x - np.asarray(truth, np.float64)[:, None]).mean(1) - spread


def score(rul, low, high, truth, samples=None) -> dict:
    """RMSE, mean error, PHM08 score, interval coverage and mean width against
    ``truth`` (and the mean CRPS when the RUL ``samples [U, K]`` are given)."""
    rul, low, high, truth = (np.asarray(v, np.float64) for v in (rul, low, high, truth))
    if truth.shape != rul.shape:
        raise ValueError(
            f"truth has {truth.size} values for {rul.size} predicted units; expected "
            "one true RUL per unit, in unit order"
        )
    err = rul - truth
    extra = {} if samples is None else {"crps": float(crps(samples, truth).mean())}
    return {
        "units": int(rul.size),
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mean_error": float(np.mean(err)),
        "phm08_score": phm08_score(err),
        "coverage": float(np.mean((truth >= low) & (truth <= high))),
        "mean_width": float(np.mean(high - low)),
        **extra,
    }


def read_truth(path: str, num_units: int | None = None) -> np.ndarray:
    """The true RULs of a one-number-per-line file (NASA's ``RUL_FD00x.txt``).

    Raises ``ValueError`` naming the file and line for a token that is not a finite
    number >= 0, and naming the counts when ``num_units`` is given and differs.
    """
    values = []
    with open(path, encoding="ascii", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            token = line.strip()
            if not token:
                continue
            try:
                value = float(token.split()[0])
            except ValueError:
                raise ValueError(
                    f"{path}, line {number}: {token!r} is not a number; expected one "
                    "true RUL (cycles >= 0) per line"
                ) from None
            if not np.isfinite(value) or value < 0:
                raise ValueError(
                    f"{path}, line {number}: {value} is not a RUL; expected a finite "
                    "number of cycles >= 0"
                )
            values.append(value)
    if num_units is not None and len(values) != num_units:
        raise ValueError(
            f"{path}: {len(values)} true RULs for {num_units} test units; expected one "
            "per unit, in unit order"
        )
    return np.array(values)
