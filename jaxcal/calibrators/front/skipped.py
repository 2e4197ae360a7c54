"""Why rows were skipped, where the reason code alone would mislead.

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

from jaxcal.calibrators.guard import REASON_CODE, REASONS
from jaxcal.calibrators.programs import compiled
from jaxcal.data.dataset import Dataset
from jaxcal.problem import Problem

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
