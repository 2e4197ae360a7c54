"""A calibrated uncertainty band for a trained policy: split conformal, per time bucket.

A policy calibrator returns one theta-hat per sample and no spread. Its error is not
stationary: the first samples of a unit carry the start-up transient (the policy
starts from the prior and needs a few steps to lock on), later samples track. So the
band is indexed by ``t``, the number of samples since the unit's first one, in
buckets ``[edges[k], edges[k + 1])`` (the last open-ended), log-spaced by default so
the transient gets its own, wider, half-width.

Per bucket and parameter the half-width is the split-conformal quantile (Vovk et al.
2005; Lei et al. 2018, "Distribution-free predictive inference", §2.2) of the
absolute errors on held-out units: with ``n`` scores the ``ceil((n + 1) level)``-th
smallest, which covers a fresh exchangeable sample with probability >= ``level``.
Exchangeability holds across units only approximately (samples of one unit are
correlated), so the guarantee is an approximation; the test units' coverage is
measured and reported by the training job, not assumed. The half-width is stored as
a Gaussian-equivalent std (half-width / z, z = 1.6449 for 90 %) so a consumer can
emit ``theta_std`` and rebuild any symmetric interval it needs.

:func:`conformal_scale` is the one split-conformal scaling of jaxcal: this band's
half-widths (scores ``|theta_hat - theta|``) and the rescaled std of
:mod:`jaxcal.calibrators.uncertainty.std_scale` (scores ``|theta_hat - theta| / std``)
are both it.

A *relative* band (``fit_band(..., scale=...)``) is the same conformal fit on the
errors divided by a per-sample scale the calibrator predicts online, and its std is
that scale times the bucket's value: for a policy built on a random-walk filter, the
filter's own std and lag bias (:mod:`jaxcal.calibrators.uncertainty.lag_scale`), which
vary from unit to unit with its drift rate and its conditions where a pooled width does
not (normalised conformal prediction, Lei et al. 2018, §5.2).

Host-side fitting (numpy, once per run) and a jittable lookup :func:`band_std` for
the deployed calibrator. Files are written through the one atomic writer.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from statistics import NormalDist

import flax.struct
import jax.numpy as jnp
import numpy as np

from jaxcal.runs.atomic import write_atomic
from jaxcal.typedefs import Array

UNCERTAINTY_FILE = "uncertainty.json"
MIN_BUCKET_SAMPLES = 20  # a bucket with fewer scores merges into its neighbour


@flax.struct.dataclass
class ThetaBand:
    """Per-bucket Gaussian-equivalent std of a calibrator's theta error.

    Attributes:
        edges: ``[K]`` int32, the sample index since a unit's first sample where
            bucket ``k`` starts; ``edges[0] == 0``, strictly increasing.
        std: ``[K, P]`` the bucket's ``level`` half-width of
            ``|theta_hat - theta|`` divided by the Gaussian ``z`` of that level
            (1.6449 for 90 %); of ``|theta_hat - theta| / scale`` for a relative
            band.
        relative: the std is a multiple of the sample's predicted error scale
            (:mod:`jaxcal.calibrators.uncertainty.lag_scale`), not theta's own.
    """

    edges: Array
    std: Array
    relative: bool = flax.struct.field(pytree_node=False, default=False)


def z_value(level: float) -> float:
    """Two-sided Gaussian quantile of ``level`` (1.6449 for 0.9)."""
    return NormalDist().inv_cdf(0.5 + level / 2)


def log_edges(length: int) -> np.ndarray:
    """``[0, 1, 2, 4, 8, ...]``: the powers of two below ``length`` (the longest
    unit's sample count) after 0."""
    powers = [2**i for i in range(max(int(length), 1).bit_length()) if 2**i < length]
    return np.asarray([0, *powers], np.int64)


def merge_small_buckets(
    edges: np.ndarray, counts: np.ndarray, min_count: int
) -> np.ndarray:
    """The bucket starts left after merging every bucket with fewer than
    ``min_count`` samples into a neighbour: a short bucket absorbs the next one
    until it is large enough, and a short last bucket joins the one before it.

    Args:
        edges: ``[K]`` bucket starts.
        counts: ``[K]`` samples per bucket.
        min_count: the smallest bucket kept on its own.

    Returns:
        ``[K']`` the kept bucket starts (``edges[0]`` always kept).
    """
    kept, kept_counts = [int(edges[0])], [int(counts[0])]
    for start, count in zip(edges[1:].tolist(), counts[1:].tolist(), strict=True):
        if kept_counts[-1] < min_count:
            kept_counts[-1] += count
        else:
            kept.append(start)
            kept_counts.append(count)
    if len(kept) > 1 and kept_counts[-1] < min_count:
        kept.pop()
    return np.asarray(kept, np.int64)


def assign_buckets(
    t: np.ndarray, edges, min_count: int, caller: str
) -> tuple[np.ndarray, np.ndarray]:
    """The buckets of scored samples at stream indices ``t`` ``[n]``: ``edges``
    (``None``: :func:`log_edges` up to the largest ``t``) checked, merged by
    :func:`merge_small_buckets`, and each sample's bucket ``[n]``.

    Raises:
        ValueError: ``edges`` do not start at 0 or do not increase (names ``caller``).
    """
    if edges is None:
        edges = log_edges(int(t.max()) + 1)
    edges = np.asarray(edges, np.int64)
    if edges.ndim != 1 or edges[0] != 0 or np.any(np.diff(edges) <= 0):
        raise ValueError(
            f"{caller}: edges must start at 0 and increase, got {edges.tolist()}"
        )
    counts = np.bincount(np.searchsorted(edges, t, side="right") - 1,
                         minlength=len(edges))  # fmt: skip
    edges = merge_small_buckets(edges, counts, min_count)
    return edges, np.searchsorted(edges, t, side="right") - 1


def conformal_quantile(scores: np.ndarray, level: float) -> np.ndarray:
    """The split-conformal quantile of ``scores`` ``[n, P]`` along axis 0: the
    ``ceil((n + 1) level)``-th smallest (the largest when that exceeds ``n``)."""
    n = scores.shape[0]
    rank = min(math.ceil((n + 1) * level), n)
    return np.sort(scores, axis=0)[rank - 1]


def conformal_scale(
    scores: np.ndarray,
    t: np.ndarray,
    *,
    level: float,
    edges,
    min_count: int,
    caller: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Split-conformal scale per time bucket: in each bucket of stream indices ``t``
    (:func:`assign_buckets`), the :func:`conformal_quantile` of the scores divided
    by the Gaussian ``z`` of ``level``, so that ``+-z * scale`` (times whatever the
    scores were normalised by) holds ``level`` of them.

    Args:
        scores: ``[n, P]`` non-conformity scores (absolute errors, or absolute errors
            over a method's std).
        t: ``[n]`` each score's stream index (samples of its unit before it).
        level: the interval's coverage target, in (0, 1).
        edges: bucket starts (``edges[0] == 0``, increasing); ``None``:
            :func:`log_edges` up to the largest ``t``.
        min_count: buckets with fewer scores merge into a neighbour; fewer scores
            in all is an error.
        caller: the public function named in errors.

    Returns:
        ``(edges [K], scale [K, P])``, ``K <= len(edges)``; ``scale`` in float64 and
        infinite where more than ``1 - level`` of a bucket's scores are.

    Raises:
        ValueError: bad ``level`` or ``edges``, or fewer than ``min_count`` scores.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"{caller}: level must be in (0, 1), got {level}")
    if len(t) < min_count:
        raise ValueError(
            f"{caller}: {len(t)} scored samples, a fit needs at least {min_count}"
        )
    edges, bucket = assign_buckets(t, edges, min_count, caller)
    q = np.stack(
        [conformal_quantile(scores[bucket == k], level) for k in range(len(edges))]
    )
    return edges, q / z_value(level)


def fit_band(
    theta_hat,
    theta_true,
    mask,
    *,
    level: float = 0.9,
    edges=None,
    min_count: int = MIN_BUCKET_SAMPLES,
    scale=None,
) -> ThetaBand:
    """Fits the per-bucket band on held-out units' whole trajectories.

    Args:
        theta_hat, theta_true: ``[U, T, P]`` calibrator output and true values; index
            ``t`` along axis 1 is the sample count since the unit's first sample.
        mask: ``[U, T]`` samples to score (real and not flagged by the calibrator).
        level: the interval's coverage target, in (0, 1).
        edges: bucket starts (``edges[0] == 0``, increasing); ``None``:
            :func:`log_edges` up to the longest unit.
        min_count: buckets with fewer samples merge into a neighbour.
        scale: ``[U, T, P]`` the calibrator's predicted error scale per sample
            (> 0 on ``mask``); given, the band is relative to it.

    Returns:
        :class:`ThetaBand` with ``K <= len(edges)`` buckets.

    Raises:
        ValueError: mismatched shapes, bad ``level`` or ``edges``, or fewer than
            ``min_count`` samples in all.
    """
    theta_hat = np.asarray(theta_hat, np.float64)
    theta_true = np.asarray(theta_true, np.float64)
    mask = np.asarray(mask, bool)
    if theta_hat.ndim != 3 or theta_hat.shape != theta_true.shape:
        raise ValueError(
            f"fit_band: theta_hat and theta_true must both be [U, T, P], got "
            f"{theta_hat.shape} and {theta_true.shape}"
        )
    if mask.shape != theta_hat.shape[:2]:
        raise ValueError(f"fit_band: mask must be [U, T] = {theta_hat.shape[:2]}, "
                         f"got {mask.shape}")  # fmt: skip
    t = np.broadcast_to(np.arange(mask.shape[1]), mask.shape)[mask]
    scores = np.abs(theta_hat - theta_true)[mask]  # [n, P]
    if scale is not None:
        scores = scores / np.asarray(scale, np.float64)[mask]
    edges, std = conformal_scale(scores, t, level=level, edges=edges,
                                 min_count=min_count, caller="fit_band")  # fmt: skip
    return ThetaBand(
        edges=jnp.asarray(edges, jnp.int32),
        std=jnp.asarray(std, jnp.float32),
        relative=scale is not None,
    )


def band_std(band: ThetaBand, t, scale=None) -> Array:
    """The std of the bucket holding ``t`` (jittable).

    Args:
        band: the fitted band.
        t: ``[]`` int32, samples since the unit's first sample (>= 0).
        scale: ``[P]`` the sample's predicted error scale (a relative band's;
            ignored by one that is not).

    Returns:
        ``[P]`` std of each parameter's error at ``t``.

    Raises:
        ValueError: a relative band without ``scale``.
    """
    # the count of edges <= t: one fused comparison (searchsorted's default is a
    # while loop, several thunks per deployed sample)
    k = jnp.sum(band.edges <= jnp.asarray(t, band.edges.dtype))
    std = band.std[jnp.clip(k - 1, 0, band.std.shape[0] - 1)]
    if not band.relative:
        return std
    if scale is None:
        raise ValueError("band_std: a relative band needs the sample's error scale")
    return std * scale


def band_coverage(
    band: ThetaBand, theta_hat, theta_true, mask, *, level: float = 0.9, scale=None
) -> tuple[float, np.ndarray]:
    """Share of ``mask``ed samples whose error lies inside the ``level`` interval
    ``|theta_hat - theta| <= z std(t)``.

    Args:
        band: the fitted band.
        theta_hat, theta_true: ``[U, T, P]``.
        mask: ``[U, T]`` samples to score.
        level: the interval's level (its ``z`` scales the std).

    Returns:
        ``(pooled over parameters, per parameter [P])``.
    """
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise ValueError("band_coverage: the mask selects no sample")
    edges, std = np.asarray(band.edges), np.asarray(band.std, np.float64)
    t = np.broadcast_to(np.arange(mask.shape[1]), mask.shape)[mask]
    half = z_value(level) * std[np.searchsorted(edges, t, side="right") - 1]
    if band.relative:
        if scale is None:
            raise ValueError("band_coverage: a relative band needs the error scale")
        half = half * np.asarray(scale, np.float64)[mask]
    err = np.abs(np.asarray(theta_hat, np.float64) - np.asarray(theta_true))[mask]
    inside = err <= half
    return float(inside.mean()), inside.mean(axis=0)


def band_to_json(band: ThetaBand) -> dict:
    """``{"edges": [K], "std": [K][P]}``: the band as JSON-ready lists, and
    ``"relative": true`` for a relative band (absent otherwise: the files of
    bands that are not read as before)."""
    doc = {
        "edges": np.asarray(band.edges).tolist(),
        "std": np.asarray(band.std, np.float64).tolist(),
    }
    return {**doc, "relative": True} if band.relative else doc


def band_from_json(doc: dict, source: str, dtype=jnp.float32) -> ThetaBand:
    """The band of :func:`band_to_json`'s dict, checked (``source`` names where the
    dict came from in the error), its std in ``dtype``.

    Raises:
        ValueError: not a band (names ``source`` and what is wrong).
    """
    try:
        edges = np.asarray(doc["edges"], np.int64)
        std = np.asarray(doc["std"], np.float64)
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(
            f"{source}: expected JSON with 'edges' [K] ints and 'std' [K, P] floats "
            f"({err!r})"
        ) from None
    if edges.ndim != 1 or std.ndim != 2 or len(edges) != len(std) or edges[0] != 0:
        raise ValueError(
            f"{source}: 'edges' must be [K] starting at 0 and 'std' [K, P], got "
            f"shapes {edges.shape} and {std.shape}"
        )
    relative = doc.get("relative", False)
    if not isinstance(relative, bool):
        raise ValueError(
            f"{source}: 'relative' must be true or false, not {relative!r}"
        )
    return ThetaBand(
        edges=jnp.asarray(edges, jnp.int32),
        std=jnp.asarray(std, dtype),
        relative=relative,
    )


def save_band(path: str | os.PathLike, band: ThetaBand, meta: dict) -> None:
    """Writes ``band`` and ``meta`` (level, units, sample count, ...) as JSON,
    atomically."""
    doc = {**meta, **band_to_json(band)}
    write_atomic(path, json.dumps(doc, indent=2) + "\n")


def load_band(run_dir: str | os.PathLike) -> ThetaBand | None:
    """The band of ``<run_dir>/uncertainty.json``; ``None`` when the file is absent.

    Raises:
        ValueError: the file is not a band (names the file and what is wrong).
    """
    path = Path(run_dir) / UNCERTAINTY_FILE
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except ValueError as err:
        raise ValueError(f"{path}: not JSON ({err})") from None
    return band_from_json(doc, str(path))
