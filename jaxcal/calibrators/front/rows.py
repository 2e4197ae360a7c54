"""From a calibration's per-group outputs back to the data's rows.

:func:`to_rows` turns the outputs of the padded unit groups of
:func:`jaxcal.calibrators.front.door.calibrate` into one
:class:`~jaxcal.calibrators.front.result.CalibrationResult` in the data's row order
(skipped
rows carry the last used row's estimate, rows before a unit's first used row the
prior); :func:`flag_notes` words the console line that counts the skipped rows per
reason, with what the outliers and the model's non-finite outputs were, and the line
naming the estimates that reached a bound of the declared box.

Every method's ``theta`` is reported inside the declared box (:func:`inside_box`):
the UKF and least squares keep their estimate there (a projected mean, projected
steps), a network or a policy may not; rows whose estimate reached a bound are
marked (``result.at_bound``) and named, never silently clipped.
"""

from __future__ import annotations

import numpy as np

from jaxcal.calibrators.front.outliers import describe_outliers
from jaxcal.calibrators.front.result import CalibrationResult
from jaxcal.calibrators.front.skipped import model_nonfinite_note
from jaxcal.calibrators.guard import MASKED, OK, REASON_CODE, REASONS
from jaxcal.data.dataset import Dataset
from jaxcal.problem import Problem

MANY_OUTLIERS = 0.01  # a share of outlier rows worth a word about the model
# an estimate this share of the box's width from a bound is at it (float32 rounds
# the projected estimate's BOX_MARGIN, 1e-6)
AT_BOUND = 1e-5


def flag_notes(result, problem, data, screened, dtype) -> list[str]:
    """The console lines: the skipped rows per reason (and what the outliers and
    non-finite model outputs were; none when every row was used), and the rows
    whose estimate reached a bound (:func:`bound_note`)."""
    return _skipped_note(result, problem, data, screened, dtype) + bound_note(
        result, problem
    )


def bound_note(result, problem) -> list[str]:
    """The line naming the rows whose estimate reached a bound of the declared box
    (per parameter and side, with the units), or nothing."""
    if result.at_bound is None or not result.at_bound.any():
        return []
    low, high = problem.theta_low, problem.theta_high
    rows = result.at_bound & result.valid
    theta = result.theta[rows]
    near = AT_BOUND * (high - low)
    parts = []
    for j, name in enumerate(problem.theta_names):
        for side, bound in (("lower", low[j]), ("upper", high[j])):
            at = np.abs(theta[:, j] - bound) <= near[j]
            n = int(np.sum(at)) if low[j] < high[j] else 0
            if n:
                parts.append(f"{name} at its {side} bound {bound:.4g} on {n} rows")
    units = np.unique(result.unit[rows])
    shown = ", ".join(str(u) for u in units[:5]) + (", ..." if len(units) > 5 else "")
    return [
        f"the estimate reached a bound of the declared box on {int(rows.sum())} of "
        f"{len(rows)} rows (units {shown}): {'; '.join(parts)}; it is held inside "
        "the box (result.at_bound marks the rows): the data may call for a value "
        "beyond the bounds (widen them if it is physical), or the model misfits there"
    ]


def inside_box(theta: np.ndarray, problem: Problem, before: np.ndarray):
    """``(theta [N, P] clipped into the problem's box, at_bound [N])``: the rows
    whose estimate reached or passed a bound, within :data:`AT_BOUND` of the box's
    width (the model-based methods hold theta :data:`~jaxcal.calibrators.
    interface.BOX_MARGIN` inside; not the rows reporting the prior, ``before``; a
    parameter whose box is one value is never "at" it)."""
    low, high = problem.theta_low, problem.theta_high
    near = AT_BOUND * (high - low)
    with np.errstate(invalid="ignore"):  # NaN: no bound reached, left NaN
        reached = ((theta <= low + near) | (theta >= high - near)) & (low < high)
    return np.clip(theta, low, high), reached.any(axis=1) & ~before


def _skipped_note(result, problem, data, screened, dtype) -> list[str]:
    """The console line counting skipped rows per reason, or nothing."""
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
    theta, at_bound = inside_box(theta, problem, before)
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
        at_bound=at_bound,
    )
