"""Scores of a calibration run over whole unit trajectories (host-side, numpy).

* theta RMSE (paper §5, "Inference Accuracy"): root mean square of theta-hat - theta
  over every valid sample of every unit, pooled over the P declared parameters, and per
  parameter;
* tracking RMSE (paper §5, "Tracking Accuracy"): x - x-hat over the valid samples
  t >= 1 (x-hat_0 = x_0 by construction), per sensor in sensor units, per sensor
  divided by the training std, and pooled over sensors in normalised units.

Samples a calibrator flagged and skipped (``CalOutput.reason``, e.g. NaN or far
outside the training range) are not scored: they repeat the last valid theta, which
says nothing about them. :func:`score_units` counts them per reason instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from jaxcal.calibrators.interface import OK, count_reasons


def describe_units(unit_ids: Sequence[int]) -> str:
    """Unit ids for printing: the list, or its count and ends when it is long."""
    ids = [int(u) for u in unit_ids]
    if len(ids) <= 12:
        return str(ids)
    return f"{len(ids)} units [{ids[0]}, {ids[1]}, ..., {ids[-1]}]"


def theta_rmse(theta_hat, theta, mask) -> tuple[float, np.ndarray]:
    """Pooled and per-parameter RMSE of ``theta_hat`` against ``theta``.

    Args:
        theta_hat, theta: ``[U, T, P]``.
        mask: ``[U, T]`` valid samples.

    Returns:
        ``(pooled, per_parameter [P])``.
    """
    err = (np.asarray(theta_hat, np.float64) - np.asarray(theta, np.float64))[
        np.asarray(mask, bool)
    ]
    if err.size == 0:
        raise ValueError("theta_rmse: the mask selects no sample")
    return float(np.sqrt(np.mean(err**2))), np.sqrt(np.mean(err**2, axis=0))


def tracking_rmse(xhat, x, mask, x_std) -> tuple[float, np.ndarray, np.ndarray]:
    """Tracking RMSE over valid samples after each unit's first one.

    Args:
        xhat, x: ``[U, T, S]`` model output and measurements.
        mask: ``[U, T]`` valid samples.
        x_std: ``[S]`` training std of each sensor (the cost's sigma).

    Returns:
        ``(pooled_normalised, per_sensor_normalised [S], per_sensor_units [S])``.
    """
    valid = np.asarray(mask, bool).copy()
    # x-hat = x on each unit's first used sample (t = 0 unless it was flagged)
    valid[np.arange(valid.shape[0]), valid.argmax(axis=1)] = False
    err = (np.asarray(x, np.float64) - np.asarray(xhat, np.float64))[valid]
    if err.size == 0:
        raise ValueError("tracking_rmse: the mask selects no sample after t = 0")
    per_sensor = np.sqrt(np.mean(err**2, axis=0))
    normalised = per_sensor / np.asarray(x_std, np.float64)
    pooled = float(np.sqrt(np.mean((err / np.asarray(x_std, np.float64)) ** 2)))
    return pooled, normalised, per_sensor


def score_units(
    theta_hat,
    xhat,
    theta,
    x,
    mask,
    x_std,
    sensors: Sequence[str],
    theta_names: Sequence[str],
    *,
    reason=None,
) -> dict:
    """Every score of one split, JSON-ready, over the valid (not flagged) samples.

    Args:
        theta_hat, xhat: ``[U, T, P]``, ``[U, T, S]`` calibrator outputs.
        theta, x: ``[U, T, P]`` labels (``None``: unlabelled data, no theta
            RMSE), ``[U, T, S]`` measurements.
        mask: ``[U, T]`` real (not padded) samples.
        x_std: ``[S]`` training std of each sensor.
        sensors, theta_names: names of the S sensors and P parameters.
        reason: ``[U, T]`` int codes (``CalOutput.reason``) or ``None`` (no flags).

    Returns:
        ``{"theta_rmse", "theta_rmse_per_param": {name: v}, "tracking_rmse_norm",
        "tracking_rmse_norm_per_sensor": {name: v}, "tracking_rmse_units":
        {name: v}, "num_samples", "num_scored", "num_flagged", "flagged":
        {reason: count}}``; ``num_samples`` counts every real sample.
    """
    mask = np.asarray(mask, bool)
    scored = mask if reason is None else mask & (np.asarray(reason) == OK)
    flagged = count_reasons(np.full(mask.shape, OK) if reason is None else reason, mask)
    if not scored.any():
        raise ValueError(
            f"score_units: every one of the {int(mask.sum())} samples was flagged "
            f"({flagged}); nothing to score"
        )
    pooled, per_param = None, {}  # theta RMSE None: no labels to score against
    if theta is not None:
        pooled, per_param = theta_rmse(theta_hat, theta, scored)
        per_param = dict(zip(theta_names, per_param.tolist(), strict=True))
    track, track_norm, track_units = tracking_rmse(xhat, x, scored, x_std)
    return {
        "theta_rmse": pooled,
        "theta_rmse_per_param": per_param,
        "tracking_rmse_norm": track,
        "tracking_rmse_norm_per_sensor": dict(
            zip(sensors, track_norm.tolist(), strict=True)
        ),
        "tracking_rmse_units": dict(zip(sensors, track_units.tolist(), strict=True)),
        "num_samples": int(mask.sum()),
        "num_scored": int(scored.sum()),
        "num_flagged": int(sum(flagged.values())),
        "flagged": flagged,
    }
