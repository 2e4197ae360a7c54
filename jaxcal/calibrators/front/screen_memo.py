"""The screening of one data set, done once per process.

The screening (:mod:`jaxcal.calibrators.front.screen`: the noise level and the outlier
rows, from up to five UKF passes) depends on the model, the problem, the rows and
the passes' filter settings, not on the method that calibrates afterwards. On a
model with an iterative solver the passes are most of a call, so a second method
on the same rows (a user comparing the UKF with least squares), or the same call
again, reuses the screening instead of repeating it: its
result is kept per (model by identity, problem, rows, filter settings, noise given
or estimated, outlier gate), the rows identified by a digest of their bytes.

New rows — another unit, one reading changed — are screened again: the digest
covers every number the screening reads (conditions, outputs, unit, time; the
problem's box, noise, normalisation and input range). A kept screening holds its
problem, hence its model, so the model's id in the key cannot be reused by another
model while the entry lives. At most :data:`MAX_KEPT` screenings and
:data:`MAX_BYTES` of their row arrays are kept (a large fleet's ``[N, S]``
innovations run to hundreds of MB): a screening larger than that is used once.
"""

from __future__ import annotations

import collections
import hashlib

import numpy as np

from jaxcal.calibrators.front.screen import Screen, screen
from jaxcal.calibrators.programs.compiled import problem_key

MAX_KEPT = 8  # screenings kept per process (least recently used dropped)
# and their row arrays at most this many bytes in all: a fleet of millions of rows
# has [N, S] arrays of hundreds of MB; one larger than this is used, not kept
MAX_BYTES = 512 * 2**20
_KEPT: collections.OrderedDict = collections.OrderedDict()
_COUNT = {"screened": 0, "reused": 0}
_LAST: list = []  # the key of the screening used last


def screened(problem, data, buckets, cfg, *, estimate: bool, threshold: float):
    """:func:`~jaxcal.calibrators.front.screen.screen`'s result, computed once per key
    (module docstring); the arguments are :func:`~jaxcal.calibrators.front.screen.
    screen`'s."""
    key = _key(problem, data, buckets.dtype, cfg, estimate, threshold)
    if key in _KEPT:
        _COUNT["reused"] += 1
        _KEPT.move_to_end(key)
    else:
        found = screen(
            problem, data, buckets, cfg, estimate=estimate, threshold=threshold
        )
        _COUNT["screened"] += 1
        if _bytes(found) > MAX_BYTES:  # too large to keep: used once
            _LAST.clear()
            return found
        _KEPT[key] = found
        while len(_KEPT) > MAX_KEPT or sum(map(_bytes, _KEPT.values())) > MAX_BYTES:
            _KEPT.popitem(last=False)
    _LAST[:] = [key]
    return _copy(_KEPT[key])


def _bytes(kept: Screen) -> int:
    """The bytes of a screening's row arrays."""
    arrays = (kept.outlier, *kept.found, kept.z, kept.used)
    return sum(a.nbytes for a in arrays if isinstance(a, np.ndarray))


def latest() -> Screen | None:
    """The screening the last call used (a study reads its innovations,
    ``experiments/misfit_battery.py``), or ``None`` (none, or too large to keep)."""
    return _copy(_KEPT[_LAST[0]]) if _LAST and _LAST[0] in _KEPT else None


def counts() -> dict:
    """``{"screened": n, "reused": m}`` in this process."""
    return dict(_COUNT)


def clear() -> None:
    """Forget every kept screening (the next call screens again)."""
    _KEPT.clear()
    _LAST.clear()


def _key(problem, data, dtype, cfg, estimate: bool, threshold: float) -> tuple:
    """Everything the screening's result depends on: the problem's program key, a
    digest of the numbers it reads, the names, the settings (by ``repr``: a
    ``state_std`` may be a dict)."""
    digest = hashlib.blake2b(digest_size=20)
    arrays = (data.w, data.x, data.unit, data.time, problem.theta_low,
              problem.theta_high, problem.noise_std, *problem.norm,
              *(problem.input_range or ()))  # fmt: skip
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    names = (data.condition_names, data.output_names, problem.noise_source)
    return (problem_key(problem, dtype), digest.hexdigest(), names, repr(cfg),
            bool(estimate), float(threshold))  # fmt: skip


def _copy(kept: Screen) -> Screen:
    """The kept screening with its row arrays copied (a caller may write to them;
    the kept one stays as computed)."""
    found = kept.found
    return kept._replace(
        outlier=kept.outlier.copy(),
        z=None if kept.z is None else kept.z.copy(),
        used=None if kept.used is None else kept.used.copy(),
        found=found._replace(mask=found.mask.copy(), z=found.z.copy(),
                             worst=found.worst.copy()),
    )  # fmt: skip
