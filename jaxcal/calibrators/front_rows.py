"""From a calibration's per-group outputs back to the data's rows.

:func:`to_rows` turns the outputs of the padded unit groups of
:func:`jaxcal.calibrators.front.calibrate` into one
:class:`~jaxcal.calibrators.result.CalibrationResult` in the data's row order (skipped
rows carry the last used row's estimate, rows before a unit's first used row the
prior); :func:`flag_notes` words the console line that counts the skipped rows per
reason, with what the outliers and the model's non-finite outputs were.
"""

from __future__ import annotations

import numpy as np

from jaxcal.calibrators.guard import MASKED, OK, REASON_CODE, REASONS
from jaxcal.calibrators.outliers import describe_outliers
from jaxcal.calibrators.result import CalibrationResult
from jaxcal.calibrators.skipped import model_nonfinite_note
from jaxcal.data.dataset import Dataset
from jaxcal.problem import Problem

MANY_OUTLIERS = 0.01  # a share of outlier rows worth a word about the model


def flag_notes(result, problem, data, screened, dtype) -> list[str]:
    """The console line counting skipped rows per reason (and what the outliers
    and non-finite model outputs were), or nothing when every row was used."""
    counts = result.num_flagged
    if not counts:
        return []
    listed = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    line = (
        f"{sum(counts.values())} of {len(result.valid)} rows flagged and skipped "
        f"({listed}; see result.valid / result.reason)"
    )
    if screened is not None and "outlier" in counts:
        line += "; " + describe_outliers(
            screened.found._replace(mask=result.reason == "outlier"),
            data.unit, problem.output_names,
        )  # fmt: skip
        share = counts["outlier"] / len(result.valid)
        if share > MANY_OUTLIERS:
            line += (
                f"; {share:.1%} of the rows, more than wild readings usually are: "
                "the model may misfit there (outlier_z=None keeps every row)"
            )
    if "state_nonfinite" in counts:
        note = model_nonfinite_note(problem, data, result.reason, dtype)
        line += "" if note is None else f"; {note}"
    return [line]


def to_rows(outs, buckets, data: Dataset, problem: Problem, method, prior_std, skip):
    """Per-group outputs -> a :class:`CalibrationResult` in the data's row order.

    Rows the method skipped repeat the last used row's estimate; rows before a
    unit's first used row report the prior (mean, and std where the method has
    one) and no model output (``nan``); outlier rows get their own reason."""
    rows = lambda values, fill=np.nan: buckets.to_rows(  # noqa: E731
        [np.asarray(v) for v in values], fill
    )
    aux = [o.aux if isinstance(o.aux, dict) else {} for o in outs]
    reason = rows([o.reason for o in outs], MASKED).astype(np.int64)
    reason[skip & (reason == MASKED)] = REASON_CODE["outlier"]
    valid = reason == OK
    before = rows(
        [np.cumsum(np.asarray(o.valid), axis=1) == 0 for o in outs], True
    ).astype(bool)
    theta = rows([o.theta for o in outs]).astype(np.float64)
    theta[before] = problem.theta_prior
    std = states = None
    if "theta_std" in aux[0]:
        std = rows([a["theta_std"] for a in aux]).astype(np.float64)
        std[before] = prior_std
    if "state" in aux[0]:
        states = rows([a["state"] for a in aux]).astype(np.float64)
        states[before] = np.nan
    xhat = rows([o.xhat for o in outs]).astype(np.float64)
    xhat[before] = np.nan
    partial = None
    if all(o.partial is not None for o in outs):
        partial = rows([o.partial for o in outs], False).astype(bool)
    return CalibrationResult(
        theta=theta,
        theta_std=std,
        states=states,
        state_names=problem.model.state_names,
        xhat=xhat,
        valid=valid,
        reason=np.asarray(REASONS)[reason],
        theta_names=problem.theta_names,
        output_names=problem.output_names,
        unit=data.unit,
        time=data.time,
        method=method,
        problem=problem,
        partial=partial,
    )
