"""Recalibrating a method's own std: one split-conformal scale per time bucket.

The UKF and least squares report a Gaussian std of theta (``aux["theta_std"]``) that
follows from their assumed noise (q, r), not from their actual error: on noise-free
data the paper's q = r = 0.01 give a std ~25x the error, so the nominal 90 %
interval covers ~100 %. The shape of the std over time (wide at the start, narrowing
as the filter locks on) is informative; its level is not. So the std is kept and
multiplied by a scale ``s`` fitted on held-out units with known theta, per bucket of
samples since a unit's start (the buckets of
:mod:`jaxcal.calibrators.uncertainty.conformal`) and per parameter: with the
normalised scores ``|theta_hat - theta| / std`` of the bucket, ``s`` is their
split-conformal ``level`` quantile (Lei et al. 2018, §2.2) divided by ``z`` (1.6449
for 90 %), so that ``+-z s std`` holds ``level`` of the
held-out errors. The estimate itself is never touched.

``t`` is the number of scored samples of the unit before this one (flagged samples
do not count): the count the deployed wrapper :func:`with_std_scale` keeps, since a
flagged sample never reaches a calibrator's ``step``.

* :func:`fit_std_scale` on padded ``[U, T, P]`` runs, :func:`fit_result_scale` on a
  :class:`~jaxcal.calibrators.front.door.CalibrationResult` of ``jaxcal.calibrate``;
* :func:`scaled_std` (jittable lookup), :func:`with_std_scale` (a calibrator whose
  ``theta_std`` is rescaled), :func:`rescale_result` (a result's ``theta_std``);
* :func:`scale_factors` (host lookup), :func:`std_coverage`: the share of samples
  inside ``+-z s std`` (``s = 1``: raw).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.struct
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator
from jaxcal.calibrators.uncertainty.conformal import (
    MIN_BUCKET_SAMPLES,
    conformal_scale,
    z_value,
)
from jaxcal.typedefs import Array


@flax.struct.dataclass
class StdScale:
    """Per-bucket multipliers of a method's reported std.

    Attributes:
        edges: ``[K]`` int32, the scored-sample count since a unit's start where
            bucket ``k`` starts; ``edges[0] == 0``, strictly increasing.
        scale: ``[K, P]`` the multiplier of ``theta_std`` in bucket ``k``.
    """

    edges: Array
    scale: Array


def stream_index(mask) -> np.ndarray:
    """``[U, T]`` the number of scored (``mask``) samples of the unit before each
    one: the ``t`` of the module docstring (meaningless where ``mask`` is False)."""
    mask = np.asarray(mask, bool)
    return np.cumsum(mask, axis=1) - 1


def normalised_scores(err: np.ndarray, std: np.ndarray) -> np.ndarray:
    """``|err| / std``; a zero std scores 0 for a zero error and inf otherwise, a
    non-finite error or std scores inf (never covered by a finite scale)."""
    err, std = np.abs(err), np.asarray(std, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        score = np.where(std > 0, err / std, np.where(err == 0, 0.0, np.inf))
    return np.where(np.isfinite(score), score, np.inf)


def _fit(scores, t, *, level, edges, min_count, caller) -> StdScale:
    """The scale of normalised ``scores`` ``[n, P]`` at stream indices ``t`` ``[n]``
    (:func:`~jaxcal.calibrators.uncertainty.conformal.conformal_scale`), which must
    be finite."""
    edges, scale = conformal_scale(scores, t, level=level, edges=edges,
                                   min_count=min_count, caller=caller)  # fmt: skip
    if not np.isfinite(scale).all():
        raise ValueError(
            f"{caller}: more than {1 - level:.0%} of a bucket's samples have a zero "
            "or non-finite std with a non-zero error: no finite scale covers them"
        )
    return StdScale(
        edges=jnp.asarray(edges, jnp.int32), scale=jnp.asarray(scale, jnp.float32)
    )


def fit_std_scale(
    theta_hat,
    theta_true,
    theta_std,
    mask,
    *,
    level: float = 0.9,
    edges=None,
    min_count: int = MIN_BUCKET_SAMPLES,
) -> StdScale:
    """Fits the per-bucket scale on held-out units' whole trajectories.

    Args:
        theta_hat: ``[U, T, P]`` a method's estimates.
        theta_true: ``[U, T, P]`` the true values.
        theta_std: ``[U, T, P]`` the method's std.
        mask: ``[U, T]`` the scored samples (real and not flagged).
        level: the interval's coverage target, in (0, 1).
        edges: bucket starts (``edges[0] == 0``, increasing); ``[0]``: one scale per
            parameter; ``None``: log-spaced
            (:func:`~jaxcal.calibrators.uncertainty.conformal.
            log_edges`).
        min_count: buckets with fewer samples merge into a neighbour.

    Returns:
        :class:`StdScale`.

    Raises:
        ValueError: mismatched shapes, bad ``level`` or ``edges``, too few samples,
            or a bucket no finite scale covers.
    """
    theta_hat = np.asarray(theta_hat, np.float64)
    std = np.asarray(theta_std, np.float64)
    mask = np.asarray(mask, bool)
    if theta_hat.ndim != 3 or not theta_hat.shape == np.shape(theta_true) == std.shape:
        raise ValueError(
            "fit_std_scale: theta_hat, theta_true and theta_std must all be "
            f"[U, T, P], got {theta_hat.shape}, {np.shape(theta_true)}, {std.shape}"
        )
    if mask.shape != theta_hat.shape[:2]:
        raise ValueError(
            f"fit_std_scale: mask must be [U, T] = {theta_hat.shape[:2]}, got "
            f"{mask.shape}"
        )
    err = (theta_hat - np.asarray(theta_true, np.float64))[mask]
    return _fit(normalised_scores(err, std[mask]), stream_index(mask)[mask],
                level=level, edges=edges, min_count=min_count,
                caller="fit_std_scale")  # fmt: skip


def scale_factors(scale: StdScale, t) -> np.ndarray:
    """``[n, P]`` the multipliers of the buckets holding stream indices ``t`` ``[n]``
    (host numpy)."""
    edges = np.asarray(scale.edges)
    k = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(edges) - 1)
    return np.asarray(scale.scale, np.float64)[k]


def scaled_std(scale: StdScale, theta_std: Array, t) -> Array:
    """``theta_std`` times the scale of the bucket holding ``t`` (jittable).

    Args:
        scale: the fitted scale.
        theta_std: ``[P]`` the method's std at this sample.
        t: ``[]`` int, scored samples of the unit before this one (>= 0).

    Returns:
        ``[P]`` the recalibrated std, in ``theta_std``'s dtype.
    """
    k = jnp.searchsorted(scale.edges, jnp.asarray(t, scale.edges.dtype), side="right")
    factor = scale.scale[jnp.clip(k - 1, 0, scale.scale.shape[0] - 1)]
    return (theta_std * factor).astype(jnp.result_type(theta_std))


def std_coverage(
    scale: StdScale | None, theta_hat, theta_true, theta_std, mask, *, level=0.9
) -> tuple[float, np.ndarray]:
    """Share of ``mask``ed samples with ``|theta_hat - theta| <= z s(t) std``.

    Args:
        scale: the fitted scale; ``None``: the raw std (``s = 1``).
        theta_hat: ``[U, T, P]`` the estimates.
        theta_true: ``[U, T, P]`` the true values.
        theta_std: ``[U, T, P]`` the std.
        mask: ``[U, T]`` the scored samples.
        level: the interval's level (its ``z``).

    Returns:
        ``(pooled over parameters, per parameter [P])``.
    """
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise ValueError("std_coverage: the mask selects no sample")
    std = np.asarray(theta_std, np.float64)[mask]
    if scale is not None:
        std = std * scale_factors(scale, stream_index(mask)[mask])
    err = np.abs(np.asarray(theta_hat, np.float64) - np.asarray(theta_true))[mask]
    inside = err <= z_value(level) * std  # a NaN counts as not covered
    return float(inside.mean()), inside.mean(axis=0)


# ------------------------------------------------------------------ deployment


@flax.struct.dataclass
class ScaledState:
    """State of :func:`with_std_scale`: the wrapped state and the samples taken."""

    inner: Any
    count: Array  # [] int32


def with_std_scale(calibrator: Calibrator, scale: StdScale) -> Calibrator:
    """``calibrator`` with its ``aux["theta_std"]`` multiplied by ``scale`` (the
    bucket of the samples it has taken); theta, x-hat and the rest unchanged.

    Raises:
        ValueError: (when traced) the calibrator reports no ``theta_std``.
    """

    def init(key, w0: Array, x0: Array) -> ScaledState:
        return ScaledState(calibrator.init(key, w0, x0), jnp.zeros((), jnp.int32))

    def step(state: ScaledState, w_t: Array, x_t: Array):
        inner, out = calibrator.step(state.inner, w_t, x_t)
        if not isinstance(out.aux, dict) or "theta_std" not in out.aux:
            raise ValueError(
                "with_std_scale: the calibrator reports no aux['theta_std'] to rescale"
            )
        std = scaled_std(scale, out.aux["theta_std"], state.count)
        out = out._replace(aux={**out.aux, "theta_std": std})
        return ScaledState(inner, state.count + 1), out

    return Calibrator(init=init, step=step, accepts_partial=calibrator.accepts_partial)


def result_index(result) -> np.ndarray:
    """``[N]`` each row's ``t`` in a :class:`~jaxcal.calibrators.front.door.
    CalibrationResult`: the valid rows of its unit before it in time (``calibrate``
    streams a unit's rows in time order). A skipped row repeats the previous valid
    row's output, so it gets that row's ``t`` (-1 before a unit's first valid row).
    """
    valid = np.asarray(result.valid, bool)
    order = np.lexsort((np.asarray(result.time), np.asarray(result.unit)))
    unit, ok = np.asarray(result.unit)[order], valid[order]
    first = np.r_[True, unit[1:] != unit[:-1]]  # a unit's first row in the order
    done = np.cumsum(ok)  # valid rows up to and including each one
    before = np.maximum.accumulate(np.where(first, done - ok, 0))
    t = np.empty(len(valid), np.int64)
    t[order] = done - before - 1
    return t


def fit_result_scale(
    result,
    theta_true,
    *,
    level: float = 0.9,
    edges=None,
    min_count: int = MIN_BUCKET_SAMPLES,
) -> StdScale:
    """:func:`fit_std_scale` on a ``jaxcal.calibrate`` result of labelled data.

    Args:
        result: a :class:`~jaxcal.calibrators.front.door.CalibrationResult` with a
            ``theta_std`` (``"ukf"``, ``"ls"``); its valid rows are scored.
        theta_true: ``[N, P]`` the true parameters of its rows, in row order.
        level: as in :func:`fit_std_scale`.
        edges: as in :func:`fit_std_scale`.
        min_count: as in :func:`fit_std_scale`.

    Example::

        val = jaxcal.calibrate(model, "val.csv", method="ukf")
        scale = fit_result_scale(val, val_theta)          # [N, P] known parameters
        new = rescale_result(jaxcal.calibrate(model, "new.csv", method="ukf"), scale)
    """
    if result.theta_std is None:
        raise ValueError(f"fit_result_scale: method {result.method!r} has no theta_std")
    theta_true = np.asarray(theta_true, np.float64)
    if theta_true.shape != result.theta.shape:
        raise ValueError(
            f"fit_result_scale: theta_true must be [N, P] = {result.theta.shape}, got "
            f"{theta_true.shape}"
        )
    rows = np.asarray(result.valid, bool)
    scores = normalised_scores(result.theta[rows] - theta_true[rows],
                               result.theta_std[rows])  # fmt: skip
    return _fit(scores, result_index(result)[rows], level=level, edges=edges,
                min_count=min_count, caller="fit_result_scale")  # fmt: skip


def rescale_result(result, scale: StdScale):
    """A copy of a ``jaxcal.calibrate`` result whose ``theta_std`` is multiplied by
    ``scale`` (rows indexed by :func:`result_index`); everything else is shared."""
    if result.theta_std is None:
        raise ValueError(f"rescale_result: method {result.method!r} has no theta_std")
    factor = scale_factors(scale, np.maximum(result_index(result), 0))
    return dataclasses.replace(result, theta_std=result.theta_std * factor)
