"""The last stage of a training run: the kept policy's uncertainty band, and the
time-to-target summary of the run's records.

The band (:mod:`jaxcal.calibrators.uncertainty.conformal`) is fitted by split conformal
on units the policy never trained on, after selection: the selected policy's theta
trajectories over them (the same jitted fleet run that scores units) give the
per-bucket absolute errors. Those units are units simulated from the model along the
validation units' conditions (:mod:`jaxcal.training.data.simulated`; no label needed)
or, for a turbofan file by default, the labelled validation units themselves
(``simulate.band``). Its coverage is then measured on the test units' whole
trajectories when they carry labels, the honest check of a band fitted elsewhere.

A policy built on a random-walk filter (``env.gauss_newton=filter``) gets a relative
band: the conformal fit of its errors over the error its filter predicts on each
sample, std and lag bias (:mod:`jaxcal.calibrators.uncertainty.lag_scale`). Its error is
mostly a per-unit lag bias (a unit's drift rate times a lag its conditions set), which a
width pooled over units misses on the fast-drifting or weakly observed units.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import OK, CalOutput
from jaxcal.calibrators.uncertainty.conformal import (
    UNCERTAINTY_FILE,
    ThetaBand,
    band_coverage,
    fit_band,
    save_band,
)
from jaxcal.data.padded import Padded
from jaxcal.training.stages.policy import TARGET_KEY

BAND_LEVEL = 0.9  # the interval the band is fitted for and its coverage checked at


def scored_mask(units: Padded, out: CalOutput) -> np.ndarray:
    """``[U, T]`` real samples the calibrator did not flag (the scored ones)."""
    mask = np.asarray(units.mask, bool)
    if out.reason is None:
        return mask
    return mask & (np.asarray(out.reason) == OK)


def scale_probe(params) -> ThetaBand | None:
    """A relative band of ones, whose std is the error the policy's filter predicts
    per sample (what a relative band is fitted on), for a policy with the filter
    feature; ``None`` for one without (its band is not relative)."""
    if not getattr(params, "gn_filter", False):
        return None
    num = params.theta_low.shape[-1]
    ones = jnp.ones((1, num), jnp.float32)
    return ThetaBand(edges=jnp.zeros(1, jnp.int32), std=ones, relative=True)


def band_runs(
    run: Callable, band_units: Padded | None, test: Padded, params, made=None
):
    """``(band_out, scales)``: the kept policy's run over the band's units and, for
    a policy on a filter (:func:`scale_probe`), the error its filter predicts on
    them and on the test units (``fit_policy_band``'s ``scales``; else ``None``).

    Args:
        run: ``(units, params, band=None) -> CalOutput`` (the run's scoring).
        band_units: the units the band is fitted on (``None``: none).
        test: the test units.
        params: the kept policy.
        made: its run over ``band_units`` already made (the validation units,
            scored when its chunk was), used where no probe is needed.
    """
    if band_units is None:
        return None, None
    probe = scale_probe(params)
    if probe is None:
        return (run(band_units, params) if made is None else made), None
    band_out = run(band_units, params, probe)  # theta is the same with the probe
    test_scale = run(test, params, probe).aux["theta_std"]
    return band_out, (band_out.aux["theta_std"], test_scale)


def fit_policy_band(
    val: Padded | None,
    val_out: CalOutput | None,
    test: Padded,
    test_out: CalOutput,
    run_dir: str | Path,
    theta_names: tuple[str, ...],
    *,
    fitted_on: str = "labelled validation units",
    scales: tuple | None = None,
    log: Callable[[str], None] = print,
) -> dict:
    """Fits the band on the validation units, writes ``uncertainty.json`` and
    measures its coverage on the test units.

    Args:
        val, val_out: the units the band is fitted on (the labelled validation
            units, or units simulated from the model:
            :mod:`jaxcal.training.data.simulated`) and the selected policy's run over
            them (``None``: there are none).
        test, test_out: the test units and the same policy's run over them.
        run_dir: the run folder.
        theta_names: names of the P parameters.
        fitted_on: what ``val`` is (written to the band's metadata).
        scales: ``(val [U, T, P], test [U', T', P])`` the error the policy's filter
            predicts per sample (:func:`scale_probe`): the band is relative to it;
            ``None``: a band of theta's own error.
        log: where notes go.

    Returns:
        The ``final.json`` fields: ``test_coverage90`` (``None`` without a band or
        without test labels), ``test_coverage90_per_param`` and ``uncertainty``
        (a summary of the file, or the reason there is none).
    """
    none = {"test_coverage90": None, "test_coverage90_per_param": {}}
    if val is None or val.theta is None:
        why = "no validation units" if val is None else "no validation theta labels"
        log(f"no uncertainty band: {why} to fit it on")
        return {**none, "uncertainty": {"file": None, "reason": why}}
    mask = scored_mask(val, val_out)
    val_scale, test_scale = (None, None) if scales is None else scales
    try:
        band = fit_band(
            val_out.theta, val.theta, mask, level=BAND_LEVEL, scale=val_scale
        )
    except ValueError as err:
        log(f"no uncertainty band: {err}")
        return {**none, "uncertainty": {"file": None, "reason": str(err)}}
    method = "split conformal per bucket of samples since a unit's start"
    if band.relative:
        method += ", of the error over the error the policy's filter predicts"
    meta = {
        "level": BAND_LEVEL,
        "method": method,
        "fitted_on": fitted_on,
        "theta_names": list(theta_names),
        "val_units": [int(u) for u in val.unit_ids],
        "num_samples": int(mask.sum()),
    }
    save_band(Path(run_dir) / UNCERTAINTY_FILE, band, meta)
    summary = {"file": UNCERTAINTY_FILE, **meta, "num_buckets": len(band.edges)}
    if test.theta is None:
        return {**none, "uncertainty": summary}
    pooled, per = band_coverage(
        band, test_out.theta, test.theta, scored_mask(test, test_out),
        level=BAND_LEVEL, scale=test_scale,
    )  # fmt: skip
    return {
        "test_coverage90": pooled,
        "test_coverage90_per_param": dict(zip(theta_names, per.tolist(), strict=True)),
        "uncertainty": summary,
    }


def time_to_target(records: list[dict], target: float | None) -> dict:
    """The ``final.json`` time-to-target fields of a run's metrics records.

    Args:
        records: the run's metrics records (``step``, ``val_theta_rmse`` and
            ``job_seconds`` on scored chunks).
        target: ``budget.target_theta_rmse`` (``None``: off).

    Returns:
        ``{"target_theta_rmse", "time_to_target_s", "time_to_target_chunk",
        "target_scorings"}``: the first scoring whose validation theta RMSE is at
        or below ``target`` (both ``None`` when none is) and how many scorings
        were read.
    """
    scored = sorted(
        (r for r in records if r.get(TARGET_KEY) is not None), key=lambda r: r["step"]
    )
    hit = next(
        (r for r in scored if target is not None and r[TARGET_KEY] <= target), None
    )
    return {
        "target_theta_rmse": target,
        "time_to_target_s": None if hit is None else hit.get("job_seconds"),
        "time_to_target_chunk": None if hit is None else int(hit["step"]),
        "target_scorings": len(scored) if target is not None else 0,
    }
