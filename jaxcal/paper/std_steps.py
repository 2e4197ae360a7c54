"""The step ``calib-<data set>-<method>``: a method's own std, recalibrated.

A method that reports a std (the UKF, least squares) gets an interval whose level
follows from its assumed noise, not from its error: on clean Dataset #1 the paper's
UKF (q = r = 0.01) reports a median std of 1.5e-4 while its error after the start-up
is ~1e-7 (the fitted scale is ~3e-4), so its nominal 90 % interval covers 99.99 % of
the test samples. :func:`calib_std_step` fits the
split-conformal scale of :mod:`jaxcal.calibrators.uncertainty.std_scale` on the suite's
validation units (the reference run's, never a test label), per bucket of samples
since a unit's start (and, for comparison, one scale for all samples), then runs the
method over the test units and measures the coverage of the raw and of the rescaled
interval. The estimate is the method's, unchanged; its test theta RMSE is reported
so that this can be checked against the ``eval-`` step.

The evaluation steps keep no per-sample std, so this step runs the method over the
test units once more.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.uncertainty.std_scale import (
    StdScale,
    fit_std_scale,
    scale_factors,
    std_coverage,
    stream_index,
)
from jaxcal.data.padded import Padded
from jaxcal.paper.compare import limit_units
from jaxcal.paper.methods import Method

LEVEL = 0.9
# reported per time range: the start-up transient, the settling, the tracking
TIME_RANGES = ((0, 32), (32, 1024), (1024, None))


def run_with_std(method: Method, units: Padded, *, seed: int) -> dict:
    """``method`` over ``units`` (clean model): per-sample theta, std and the scored
    mask, plus the run's seconds (compilation included)."""
    dtype = method.dtype
    keys = jax.random.split(jax.random.key(seed), len(units.lengths))
    tic = time.perf_counter()
    with jax.enable_x64(dtype == np.float64):
        out = method.run(
            units.w.astype(dtype), units.x.astype(dtype), units.mask, keys,
            jnp.asarray(1.0, dtype), jnp.asarray(0.0, dtype),
        )  # fmt: skip
        out = jax.block_until_ready(out)
    if out.aux is None or "theta_std" not in out.aux:
        raise ValueError(f"method {method.name!r} reports no aux['theta_std']")
    return {
        "theta": np.asarray(out.theta, np.float64),
        "std": np.asarray(out.aux["theta_std"], np.float64),
        "scored": np.asarray(units.mask, bool) & np.asarray(out.valid, bool),
        "seconds": time.perf_counter() - tic,
    }


def _scale_json(scale: StdScale) -> dict:
    return {
        "edges": np.asarray(scale.edges).tolist(),
        "scale": np.asarray(scale.scale, np.float64).tolist(),
    }


def coverage_report(
    scales: dict, run: dict, units: Padded, names: tuple[str, ...]
) -> dict:
    """Coverage of the raw std (``None`` in ``scales``) and of each scale on one
    split: pooled, per parameter, per time range, and the median std."""
    theta, std, scored = run["theta"], run["std"], run["scored"]
    t = stream_index(scored)
    report = {}
    for label, scale in scales.items():
        pooled, per = std_coverage(scale, theta, units.theta, std, scored, level=LEVEL)
        by_time = {}
        for lo, hi in TIME_RANGES:
            part = scored & (t >= lo) & (t < (hi or np.iinfo(np.int64).max))
            if part.any():
                by_time[f"{lo}-{hi or 'end'}"] = std_coverage(
                    scale, theta, units.theta, std, part, level=LEVEL
                )[0]
        factor = 1.0 if scale is None else scale_factors(scale, t[scored])
        report[label] = {
            "coverage90": pooled,
            "coverage90_per_param": dict(zip(names, per.tolist(), strict=True)),
            "coverage90_by_time": by_time,
            "theta_std_median": float(np.median(std[scored] * factor)),
        }
    return report


def _rmse(run: dict, units: Padded) -> float:
    err = (run["theta"] - units.theta)[run["scored"]]
    return float(np.sqrt(np.mean(err**2)))


def calib_std_step(suite, name: str, *, seed: int, edges=None) -> dict:
    """Fit ``name``'s std scale on the suite's validation units; measure the raw
    and recalibrated 90 % coverage on its test units.

    Args:
        suite: a :class:`~jaxcal.paper.suite.Suite`.
        name: a method reporting ``aux["theta_std"]`` (``"UKF"``, ``"LS"``).
        seed: root of the per-unit keys.
        edges: bucket starts of the scale (``None``: log-spaced, as the policy's
            band).

    Returns:
        JSON-ready: ``coverage90`` (recalibrated, test) and ``coverage90_raw``,
        ``scale`` (per bucket) and ``scale_one`` (one for all samples) with their
        validation and test coverage in ``coverage``, the test ``theta_rmse``
        (the method's own estimate) and the units and samples used.

        Without validation units: ``coverage90`` None and a ``note``.

    Raises:
        ValueError: the method reports no std.
    """
    val = suite.data.val
    if val is None or len(val.lengths) == 0:  # nothing to fit on: said, not guessed
        return {"method": name, "level": LEVEL, "coverage90": None,
                "coverage90_raw": None, "val_units": [],
                "note": "the reference run holds out no validation unit"}  # fmt: skip
    method = suite.method(name)
    names = suite.problem.theta_names
    val = limit_units(val, max_steps=suite.cfg.max_steps)  # the test units' cut
    test = suite.test_units()
    val_run = run_with_std(method, val, seed=seed)
    args = (val_run["theta"], val.theta, val_run["std"], val_run["scored"])
    scales = {
        "raw": None,
        "buckets": fit_std_scale(*args, level=LEVEL, edges=edges),
        "one": fit_std_scale(*args, level=LEVEL, edges=[0]),
    }
    test_run = run_with_std(method, test, seed=seed)
    on_val = coverage_report(scales, val_run, val, names)
    on_test = coverage_report(scales, test_run, test, names)
    return {
        "method": name,
        "level": LEVEL,
        "coverage90": on_test["buckets"]["coverage90"],
        "coverage90_raw": on_test["raw"]["coverage90"],
        "coverage90_one_scale": on_test["one"]["coverage90"],
        "scale": _scale_json(scales["buckets"]),
        "scale_one": _scale_json(scales["one"]),
        "coverage": {"val": on_val, "test": on_test},
        "theta_rmse": _rmse(test_run, test),
        "val_theta_rmse": _rmse(val_run, val),
        "val_units": val.unit_ids.tolist(),
        "val_samples": int(val_run["scored"].sum()),
        "test_units": test.unit_ids.tolist(),
        "test_samples": int(test_run["scored"].sum()),
        "val_run_s": val_run["seconds"],
        "test_run_s": test_run["seconds"],
    }
