"""Run any method over whole test trajectories and measure it like every other one.

:func:`evaluate_method` runs a :class:`~jaxcal.paper.methods.Method` through every
unit of a split (its jitted fleet runner: ``lax.scan`` over time, ``vmap`` over units),
with the model perturbation of the paper's robustness tables if asked, and returns
the scores of :func:`jaxcal.training.scoring.trajectories.score_units` (theta RMSE
pooled and per
parameter, tracking RMSE normalised by the training std and in sensor units) plus
per-unit theta RMSE and the cost of the run:

* ``compile_s``: tracing and compiling the fleet runner (ahead of time, excluded);
* ``run_s`` and ``batched_samples_per_s``: one execution over all units at once.

A method that reports its uncertainty (``aux["theta_std"]``, a Gaussian-equivalent
std: the UKF's, a policy's band) also gets ``coverage90``, the share of scored samples
whose error is within the 90 % interval ``+-1.6449 std`` (:func:`interval_coverage`),
and ``theta_std_median``: an honest band covers about 90 %, a narrow one much less.

:func:`measure_latency` is the single-stream cost of the paper's Table "time": one
sample at a time through the method's jitted ``step``, host numpy in and out, blocking
— the same harness for every method. The paper reports seconds per sample on one CPU
thread; this machine has two shared cores.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator, count_reasons
from jaxcal.data.padded import Padded
from jaxcal.paper.methods import Method
from jaxcal.problem import Problem
from jaxcal.training.scoring.trajectories import score_units, theta_rmse

Z90 = 1.6449  # two-sided 90 % quantile of the standard normal


def interval_coverage(
    theta: np.ndarray,
    theta_std: np.ndarray,
    truth: np.ndarray,
    mask: np.ndarray,
    names: tuple[str, ...] | list[str],
    *,
    z: float = Z90,
) -> dict:
    """How often the interval ``theta +- z std`` holds the true theta.

    Args:
        theta: ``[U, T, P]`` estimates.
        theta_std: ``[U, T, P]`` their Gaussian-equivalent std.
        truth: ``[U, T, P]`` true values.
        mask: ``[U, T]`` the scored samples (the theta RMSE's mask).
        names: the ``P`` parameter names.
        z: the interval's half-width in stds (``Z90``: the 90 % interval).

    Returns:
        ``{"coverage90", "coverage90_per_param", "theta_std_median"}``: the share of
        scored samples covered, averaged over parameters and per parameter, and the
        median std over scored samples and parameters (None without scored samples).
    """
    mask = np.asarray(mask, bool)
    std = np.asarray(theta_std, np.float64)
    if std.shape != np.shape(theta):
        raise ValueError(
            f"aux['theta_std'] must be shaped like theta {np.shape(theta)}, got "
            f"{std.shape}"
        )
    if not mask.any():
        return {"coverage90": None, "coverage90_per_param": None,
                "theta_std_median": None}  # fmt: skip
    err = np.abs(np.asarray(theta, np.float64) - truth)[mask]  # [N, P]
    # a NaN std or estimate counts as not covered
    covered = (err <= z * std[mask]).mean(axis=0)
    return {
        "coverage90": float(covered.mean()),
        "coverage90_per_param": dict(zip(names, covered.tolist(), strict=True)),
        "theta_std_median": float(np.median(std[mask])),
    }


class MethodRun(NamedTuple):
    """Scores (JSON-ready) and the outputs behind them (host numpy)."""

    scores: dict
    theta: np.ndarray  # [U, T, P]
    xhat: np.ndarray  # [U, T, S]


def limit_units(
    units: Padded,
    *,
    max_units: int | None = None,
    max_steps: int | None = None,
    seed: int = 0,
) -> Padded:
    """A seeded subset of ``max_units`` units, each cut to ``max_steps`` samples.

    Every method of a table is scored on the same limited split. The subset is drawn
    at random (then kept in unit order): unit ids of a factorial design follow its
    levels, so the first ids alone would be a biased sample. ``None`` keeps all.
    """
    num = len(units.lengths)
    if max_units is not None and max_units < num:
        pick = jax.random.choice(jax.random.key(seed), num, (max_units,), replace=False)
        keep = np.sort(np.asarray(pick))
    else:
        keep = np.arange(num)
    steps = units.x.shape[1] if max_steps is None else min(max_steps, units.x.shape[1])
    lengths = np.minimum(units.lengths[keep], steps).astype(np.int32)
    steps = int(lengths.max())
    return Padded(
        *(a[keep, :steps] for a in units[:3]),
        lengths=lengths,
        unit_ids=units.unit_ids[keep],
    )


def _timed_run(method: Method, args: tuple):
    """``(output, compile_s, run_s)`` of the method's fleet runner on ``args``:
    compiled ahead of time (excluded from the run), then one blocking execution."""
    tic = time.perf_counter()
    compiled = method.run.lower(*args).compile()
    compile_s = time.perf_counter() - tic
    tic = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return out, compile_s, time.perf_counter() - tic


def _theta_scores(theta, truth, mask, scored, reason, problem: Problem) -> dict:
    """The scores without a model output: theta RMSE pooled and per parameter, the
    sample counts and the flagged samples' reasons."""
    pooled, per_param = theta_rmse(theta, truth, scored)
    scores = {
        "theta_rmse": pooled,
        "theta_rmse_per_param": dict(
            zip(problem.theta_names, per_param.tolist(), strict=True)
        ),
        "tracking_rmse_norm": None,
        "num_samples": int(mask.sum()),
        "num_scored": int(scored.sum()),
        "flagged": count_reasons(reason, mask),
    }
    scores["num_flagged"] = sum(scores["flagged"].values())
    return scores


def evaluate_method(
    method: Method,
    units: Padded,
    problem: Problem,
    *,
    seed: int = 0,
    bias: float = 1.0,
    noise_sigma: float = 0.0,
    model_output: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> MethodRun:
    """Scores of one method over whole unit trajectories.

    Args:
        method: the method.
        units: the split (``[U, T, ...]``, padded, with lengths).
        problem: sensors, parameter names and normalisation of the data set.
        seed: root of the per-unit keys (only stochastic models use them).
        bias: model-output bias alpha (1: none).
        noise_sigma: model-output noise alpha_eta in training-std units (0: none).
        model_output: ``(w [N, W], theta [N, P]) -> x [N, S]`` evaluated at the valid
            samples when the method gives no model output (E2E); without it such a
            method gets no tracking score.
    """
    dtype = method.dtype
    w, x = units.w.astype(dtype), units.x.astype(dtype)
    mask = units.mask
    keys = jax.random.split(jax.random.key(seed), len(units.lengths))
    settings = (jnp.asarray(bias, dtype), jnp.asarray(noise_sigma, dtype))
    out, compile_s, run_s = _timed_run(method, (w, x, mask, keys, *settings))
    theta = np.asarray(out.theta, np.float64)
    xhat = np.asarray(out.xhat, np.float64)
    reason = np.asarray(out.reason)
    scored = mask & np.asarray(out.valid)  # flagged samples are counted, not scored
    if method.model_free and model_output is not None:
        xhat = np.full(x.shape, np.nan)
        xhat[scored] = model_output(units.w[scored], theta[scored])
    finite = np.isfinite(xhat[scored]).all()
    if finite:
        scores = score_units(
            theta, xhat, units.theta, units.x, mask, problem.norm.x_std,
            problem.output_names, problem.theta_names, reason=reason,
        )  # fmt: skip
    else:  # no model output (or a diverged one): theta scores only
        scores = _theta_scores(theta, units.theta, mask, scored, reason, problem)
    per_unit = np.sqrt(
        np.nanmean(
            np.where(scored[..., None], (theta - units.theta) ** 2, np.nan), axis=(1, 2)
        )
    )
    scores.update(
        method=method.name,
        theta_finite=bool(np.isfinite(theta[scored]).all()),
        theta_rmse_per_unit=dict(
            zip(map(str, units.unit_ids.tolist()), per_unit.tolist(), strict=True)
        ),
        units=units.unit_ids.tolist(),
        bias=bias,
        noise_sigma=noise_sigma,
        seed=seed,
        compile_s=compile_s,
        run_s=run_s,
        batched_samples_per_s=int(mask.sum()) / run_s,
        batched_units=len(units.lengths),
        info=method.info,
    )
    if out.aux is not None and "theta_std" in out.aux:  # methods with a std only
        scores.update(
            interval_coverage(
                theta, out.aux["theta_std"], units.theta, scored, problem.theta_names
            )
        )
    return MethodRun(scores=scores, theta=theta, xhat=xhat)


def measure_latency(
    method: Method,
    units: Padded,
    *,
    repeats: int,
    seed: int = 0,
    calibrator: Calibrator | None = None,
) -> dict:
    """Single-stream seconds per sample of ``method`` as deployed (clean model).

    The method's deployed form (:meth:`Method.deploy`: the unperturbed model, so no
    noise key in its state, and for a policy on F the solve warm-started from the
    previous sample, the form ``StreamingCalibrator.step`` runs) is jitted alone and
    called on consecutive samples of the first unit (cycled), numpy in and out, after
    a compiling warm-up call. Its agreement with the scored form is tested
    (``tests/paper/test_stream_form.py``, ``tests/paper/test_evaluation.py``) and
    measured by ``experiments/cpubench/engine_latency.py``; compiling both here
    would cost a second engine program per step.

    ``calibrator``: another form of the method to time the same way (e.g. its
    perturbable ``build(1, 0)``); ``None``: the deployed one.

    Returns:
        ``{"median_s", "min_s", "repeats", "stream_form", "deploy_form"}``
        (``stream_form``: the model's solve is warm-started; ``deploy_form``: timed
        in the deployed form, not the perturbable one with its noise key).
    """
    deployed = calibrator is None
    calibrator = method.deploy() if deployed else calibrator
    length = int(units.lengths[0])
    w = units.w[0, :length].astype(method.dtype)
    x = units.x[0, :length].astype(method.dtype)
    step = jax.jit(calibrator.step)
    state = calibrator.init(jax.random.key(seed), w[0], x[0])
    state, out = step(state, w[0], x[0])
    np.asarray(out.theta)  # compiled and finished
    times = np.empty(repeats)
    for i in range(repeats):  # the harness is the stream: one host call per sample
        t = (i + 1) % length
        tic = time.perf_counter()
        state, out = step(state, w[t], x[t])
        np.asarray(out.theta)
        times[i] = time.perf_counter() - tic
    return {
        "median_s": float(np.median(times)),
        "min_s": float(times.min()),
        "repeats": repeats,
        "stream_form": method.warm and deployed,
        "deploy_form": deployed,
    }


def stacked(values: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Valid samples of all units, one after the other (the paper's figures).

    Args:
        values: ``[U, T, ...]``.
        mask: ``[U, T]``.

    Returns:
        ``(values [N, ...], starts [U])`` with ``starts`` the index where each unit
        begins.
    """
    mask = np.asarray(mask, bool)
    counts = mask.sum(axis=1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return np.asarray(values)[mask], starts
