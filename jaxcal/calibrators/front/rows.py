"""From a calibration's per-group outputs back to the data's rows, and why rows were
skipped.

:func:`to_rows` turns the outputs of the padded unit groups of
:func:`jaxcal.calibrators.front.door.calibrate` into one
:class:`~jaxcal.calibrators.front.result.CalibrationResult` in the data's row order
(skipped rows carry the last used row's estimate, rows before a unit's first used row
the prior); :func:`flag_notes` words the console line that counts the skipped rows
per reason, with what the outliers and the model's non-finite outputs were, and the
line naming the estimates that reached a bound of the declared box.

Every method's ``theta`` is reported inside the declared box (:func:`inside_box`):
the UKF and least squares keep their estimate there (a projected mean, projected
steps), a network or a policy may not; rows whose estimate reached a bound are
marked (``result.at_bound``) and named, never silently clipped.

A calibrator flags a row ``state_nonfinite`` when its update is not finite. That has
two causes with different fixes: the model itself returns NaN / Inf there (its
formula breaks in part of the parameter box or of the conditions: fix the model or
narrow its bounds), or the arithmetic of the update fails although the model is
finite (a noise std so small that the filter's gain overflows: give a larger noise
or use float64). :func:`model_nonfinite_note` tells them apart by evaluating the model
at the flagged rows' conditions, at the nominal parameters, at each parameter's
bounds and where the UKF's sigma points reach beyond them;
:func:`nothing_valid_error` is the error of a calibration that kept no row.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.front.outliers import describe_outliers
from jaxcal.calibrators.front.result import CalibrationResult
from jaxcal.calibrators.guard import MASKED, OK, REASON_CODE, REASONS
from jaxcal.calibrators.programs import compiled
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


_STATE_NONFINITE = REASON_CODE["state_nonfinite"]
# the note's ending when the model breaks only outside the parameter bounds
OUTSIDE = ", outside the parameter bounds"


def probe_thetas(problem: Problem) -> np.ndarray:
    """``[4P + 1, P]``: the prior, then each parameter at its low and its high bound
    with the others at the prior, then at the prior -+ ``sqrt(P)`` half-widths: where
    the UKF's sigma points reach with its defaults (``prior_std`` 1 half-width,
    ``alpha`` 1), beyond the bounds for a parameter whose prior is near one."""
    prior = problem.theta_prior
    reach = np.sqrt(len(prior)) * problem.theta_half_width
    points = [prior]
    for j in range(len(prior)):
        for value in (problem.theta_low[j], problem.theta_high[j]):
            points.append(np.where(np.arange(len(prior)) == j, value, prior))
    for j in range(len(prior)):
        for value in (prior[j] - reach[j], prior[j] + reach[j]):
            points.append(np.where(np.arange(len(prior)) == j, value, prior))
    return np.stack(points)


def model_nonfinite(problem: Problem, w: np.ndarray, dtype) -> tuple:
    """Where the model's outputs are not finite at the :func:`probe_thetas`.

    A model with memory is probed one step from its initial state at the row.

    Args:
        problem: the problem (its restricted model).
        w: ``[M, W]`` conditions.
        dtype: the float dtype of the calibration.

    Returns:
        ``(bad [M] bool, theta [M, P])``: a row is bad when some probe gives a
        non-finite output; ``theta`` is the first such probe of each row.
    """
    thetas = probe_thetas(problem)

    def build():
        tr = problem.transition()

        def outputs(w_r, theta):
            return tr.step(tr.init(w_r, theta), w_r, theta)[1]

        return jax.jit(jax.vmap(jax.vmap(outputs, (None, 0)), (0, None)))

    # one program per problem and process (the turbofan's takes 17 s to trace)
    grid = compiled.cached("probe", problem, None, dtype, build)
    rows = len(w)  # padded to a power of two: few shapes, few programs
    padded = np.concatenate(
        [w, np.repeat(w[:1], (1 << (rows - 1).bit_length()) - rows, 0)]
    )
    x = np.asarray(grid(jnp.asarray(padded, dtype), jnp.asarray(thetas, dtype)))[:rows]
    broken = ~np.all(np.isfinite(x), axis=-1)  # [M, K]
    return broken.any(axis=1), thetas[np.argmax(broken, axis=1)]


def model_nonfinite_note(
    problem: Problem, data: Dataset, reason: np.ndarray, dtype
) -> str | None:
    """``"the model returns non-finite outputs on N of M rows (first: ...)"`` for
    the rows flagged ``state_nonfinite`` where the model is the cause, or ``None``.

    Args:
        problem: the problem.
        data: the rows (as calibrated).
        reason: ``[N]`` reason names or codes of the rows.
        dtype: the float dtype of the calibration.
    """
    reason = np.asarray(reason)
    flagged = (
        reason == "state_nonfinite"
        if reason.dtype.kind in "US"
        else reason == _STATE_NONFINITE
    )
    rows = np.flatnonzero(flagged & np.all(np.isfinite(data.w), axis=1))
    if not rows.size:
        return None
    bad, theta = model_nonfinite(problem, data.w[rows], dtype)
    if not bad.any():
        return None
    first = int(np.argmax(bad))
    r = rows[first]
    w = ", ".join(
        f"{n}={v:.6g}" for n, v in zip(data.condition_names, data.w[r], strict=True)
    )
    th = ", ".join(
        f"{n}={v:.6g}" for n, v in zip(problem.theta_names, theta[first], strict=True)
    )
    outside = np.any(
        (theta[first] < problem.theta_low) | (theta[first] > problem.theta_high)
    )
    return (
        f"the model returns non-finite outputs on {int(bad.sum())} of "
        f"{data.num_rows} rows (first: row {int(data.row[r])}, unit "
        f"{int(data.unit[r])}, w=({w}), theta=({th}))" + (OUTSIDE if outside else "")
    )


def nothing_valid_error(
    problem: Problem, data: Dataset, reason: np.ndarray, dtype, what: str
) -> ValueError:
    """The error of a calibration step that kept no row, with the cause.

    Args:
        problem: the problem (its noise is named when the update is the cause).
        data: the rows.
        reason: ``[N]`` int reason codes of the rows.
        dtype: the float dtype of the calibration.
        what: what failed (``"calibrate"``, ``"noise estimation"``, ...).
    """
    codes, counts = np.unique(np.asarray(reason), return_counts=True)
    listed = ", ".join(f"{REASONS[c]} {n}" for c, n in zip(codes, counts, strict=True))
    message = f"{what}: every one of the {data.num_rows} rows was skipped ({listed})"
    if _STATE_NONFINITE not in codes:
        return ValueError(
            f"{message}: no row passed the input checks (result.reason says which); "
            "check the data's columns and units against the model's condition range"
        )
    note = model_nonfinite_note(problem, data, reason, dtype)
    if note is not None and note.endswith(OUTSIDE):
        return ValueError(
            f"{message}: {note}; make the model finite there (the UKF's sigma points "
            "reach sqrt(P) prior stds past the prior, beyond the bounds), or give the "
            "UKF a smaller prior_std"
        )
    if note is not None:
        return ValueError(
            f"{message}: {note}; fix the model there or narrow the parameter bounds"
        )
    noise = ", ".join(
        f"{n}={s:.3g}"
        for n, s in zip(problem.output_names, problem.noise_std, strict=True)
    )
    size = ", ".join(
        f"{n}={s:.3g}"
        for n, s in zip(problem.output_names, np.abs(data.x).max(0), strict=True)
    )
    return ValueError(
        f"{message}: the model is finite at these rows (nominal parameters and "
        f"bounds), so the calibrator's update itself overflowed: a noise std of "
        f"({noise}) is too small for {np.dtype(dtype).name} arithmetic on outputs "
        f"of size ({size}); give a larger noise= (or enable float64)"
    )
