"""Screening before calibration: the noise level and the outlier rows, by UKF passes.

:func:`jaxcal.calibrate` runs the unscented Kalman filter over every unit before the
chosen method (it costs ``2P + 1`` model evaluations a row, where least squares'
Jacobians cost far more on a model with an iterative solver) and reads two things
off its passes:

* **Outliers.** A reading the filter did not expect: its innovation ``x_t -
  E[x_t | past]`` (the prediction before the row is used, so the row cannot explain
  itself away) beyond :data:`~jaxcal.calibrators.front.outliers.OUTLIER_Z` times its
  predicted std, on any output — the Kalman filter's validation gate (Bar-Shalom,
  Li & Kirubarajan 2001, "Estimation with Applications to Tracking and Navigation",
  sec. 5.4), per output. A wild row drags the filter, so the rows after it look
  wild too: the first pass proposes candidates, the second pass skips them and judges
  every row again from the filter state carried past the skipped ones (the UKF step
  evaluated at each row from the state before it,
  :func:`~jaxcal.calibrators.programs.compiled.filter_program`), and only
  candidates still beyond the gate are flagged (never a new row: skipping the start
  of a real change would make the rest of it look wild, one pass after another).
  The innovations are taken about their robust centre and over their robust scale
  (:func:`~jaxcal.calibrators.front.outliers.robust_scale`), so a model misfit, which
  shifts and widens all of them, is not an outlier. With a given noise
  (``noise=``) that scale is at least 1: a row is judged against the given noise,
  or against the data's own spread where that is wider (and a note says so).
* **The noise** (when not given), from the one-step innovations ``nu_t = x_t -
  E[x_t | past]`` of each unit's settled rows (each unit's first :data:`SETTLE`
  share left out), pooled over units with the hard-rejection estimator of
  :func:`~jaxcal.calibrators.front.outliers.robust_noise`, outlier rows left out. The
  update moves the prediction of output ``s`` by a share ``k_s`` of its innovation
  (``k = 1 - R / S``, ``S`` the innovation's predicted variance: the diagonal of
  the filter's ``HK`` where the outputs' innovations are uncorrelated), and a
  parameter that follows the noise leaves innovations correlated with the last
  ones: for a slowly drifting truth, ``var(nu) = 2 R / (2 - k)`` whatever noise the
  pass assumed (the steady state of ``e_t = (1 - k) e_{t-1} + k n_t``, ``nu_t = n_t -
  e_{t-1}``), so ``R = var(nu) (2 - k) / 2``. A truth that drifts by ``D`` in
  variance per row adds ``D / (2k)``, and a model misfit adds its share: both widen
  the noise, never narrow it. (The post-fit residual is narrowed by the share the
  update absorbs: where one parameter alone explains an output the filter follows
  the noise and the residual is nearly nothing.) Schedule: a first level from a pass
  on a provisional noise (1 % of each output's robust spread), rejecting with Hampel's
  X84 rule (:data:`X84`) so that a wild row's wake is not averaged in, and a pass on
  that level; the outlier passes on that level; the noise from the innovations of the
  last pass, which skipped the outliers (where a candidate was cleared, one more pass
  skipping only the outliers): two to four passes. The level is not found
  again with the outliers skipped: the estimate does not depend on the noise a pass
  assumes.

The UKF is compiled once per process for all passes and all calls (the noise and
the outputs' centre are arguments of the compiled program,
:mod:`jaxcal.calibrators.programs.compiled`), group by group of the
:class:`~jaxcal.data.buckets.Buckets`.

So a few wild rows change neither the noise of the other units nor their results,
and their own unit's stream skips them (reason ``outlier``).

Two faults are judged per output, not per row:

* **A stuck sensor.** An output that repeats one reading for
  :data:`~jaxcal.calibrators.front.outliers.STUCK_RUN` rows or more (a quantised output,
  which repeats most of its readings, excepted:
  :func:`~jaxcal.calibrators.front.outliers.stuck_runs`) while the filter expects it to
  move (a value of the run beyond the gate) is a frozen sensor, not a row of wild
  readings: judged per row, every row of the run would be skipped, its good outputs
  with it. The run's readings of that output are left out (missing: the rows are
  partial, used on their other outputs; :attr:`Screen.data`), the screening starts
  again without them, and a note names the output, unit and rows.
* **Too few rows for the noise.** The noise estimated from fewer than
  :data:`MIN_NOISE_ROWS` settled readings of an output can be far off: a note
  names the outputs and their counts and asks for ``noise=``.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.front.outliers import (
    OutlierRows,
    StuckRun,
    outlier_rows,
    robust_centre,
    robust_noise,
    robust_scale,
    stuck_runs,
)
from jaxcal.calibrators.front.rows import nothing_valid_error
from jaxcal.calibrators.guard import MASKED, OK
from jaxcal.calibrators.methods.on_model import model_inputs
from jaxcal.calibrators.methods.ukf import UKF, ukf_program
from jaxcal.data.buckets import Buckets, bucket_units
from jaxcal.data.dataset import Dataset
from jaxcal.problem import PROVISIONAL_NOISE_SHARE, Problem

SETTLE = 0.1  # share of each unit's rows left out of the noise while the filter settles
NOISE_FLOOR_REL = 1e-6  # noise floor relative to the output's robust spread (or 1)
# the first pass's noise: the one provisional share of the output's robust spread
PROVISIONAL_REL = PROVISIONAL_NOISE_SHARE
X84 = 3.5  # Hampel's X84 rejection rule: 5.2 MADs, i.e. 3.5 Gaussian std
WIDE_INNOVATIONS = 3.0  # typical |innovation| / predicted std worth a note
MIN_NOISE_ROWS = 20  # settled readings of an output below which its noise is noted


class Screen(NamedTuple):
    """What :func:`screen` found.

    Attributes:
        problem: the problem with its noise (given, or estimated).
        outlier: ``[N]`` bool rows flagged as outliers.
        found: the :class:`~jaxcal.calibrators.front.outliers.OutlierRows` behind it.
        notes: what the screening noticed (a given noise far too small).
        z: ``[N, S]`` the last pass's one-step innovations over their predicted
            std (``nan``: a missing output), or ``None`` (no row used); their
            colour is the model's misfit
            (:mod:`jaxcal.calibrators.uncertainty.misfit_check`).
        used: ``[N]`` bool, the rows that pass used (outliers skipped), or ``None``.
        data: the rows with a stuck sensor's readings left out (``nan``), which the
            method must calibrate on, and ``buckets`` them padded; ``None``: the
            rows as given.
    """

    problem: Problem
    outlier: np.ndarray
    found: OutlierRows
    notes: tuple[str, ...]
    z: np.ndarray | None = None
    used: np.ndarray | None = None
    data: Dataset | None = None
    buckets: Buckets | None = None


class _Pass(NamedTuple):
    """One UKF pass, per row (``N``)."""

    z: np.ndarray  # [N, S] innovation / its predicted std
    innovation: np.ndarray  # [N, S] x - E[x | past], output units (nan: missing)
    absorbed: np.ndarray  # [N, S] k: the share of it the update absorbs
    valid: np.ndarray  # [N] used by the pass
    judged: np.ndarray  # [N] used, or skipped as a candidate outlier
    reason: np.ndarray  # [N] int codes (a skipped candidate: masked)
    skip: np.ndarray  # [N] the rows this pass skipped as candidates


def screen(
    problem: Problem,
    data: Dataset,
    buckets: Buckets,
    cfg: UKF,
    *,
    estimate: bool,
    threshold: float,
) -> Screen:
    """The noise (estimated when ``estimate``) and the outlier rows (module doc).

    Args:
        problem: the problem; its noise is the given one unless ``estimate``.
        data: the rows, as calibrated (``buckets`` index them).
        buckets: the rows as padded unit groups.
        cfg: the UKF passes' settings (:class:`~jaxcal.calibrators.methods.ukf.UKF`).
        estimate: estimate the noise (else judge against ``problem.noise_std``).
        threshold: the gate in standard deviations (``inf``: flag nothing).

    Returns:
        :class:`Screen`.

    Raises:
        ValueError: no row could be used (with the cause), or fewer than two rows
            to estimate the noise from.
    """
    runs = stuck_runs(data.x, data.unit, data.time) if threshold < np.inf else []
    found = _screen(problem, data, buckets, cfg, estimate, threshold, runs)
    if isinstance(found, Screen):
        return found
    data, notes = found  # a stuck sensor's readings left out: screened again
    buckets = bucket_units(data, buckets.dtype)
    found = _screen(problem, data, buckets, cfg, estimate, threshold, [])
    return found._replace(notes=(*notes, *found.notes), data=data, buckets=buckets)


def _screen(problem, data, buckets, cfg, estimate, threshold, runs):
    """:func:`screen` on these rows, or, where the first pass finds some of the
    stuck ``runs`` beyond the gate, ``(data, notes)``: the rows with those runs
    left out, to be screened again."""
    none = np.zeros(data.num_rows, bool)
    ukf = _pass_function(problem, data, cfg, buckets.dtype)
    run = functools.partial(_pass, ukf, data=data, buckets=buckets, r=cfg.filter.r)
    settled = _settled(buckets)
    if estimate:
        spread = np.nan_to_num(robust_scale(data.x))
        # more than half the readings equal (a quantised or stuck output): its std
        spread = np.where(spread > 0, spread, problem.norm.x_std)
        floor = NOISE_FLOOR_REL * np.maximum(spread, 1.0)
        provisional = np.maximum(PROVISIONAL_REL * spread, floor)

        def level(skip):
            """A first noise level from a pass on the provisional one (the X84
            rule rejects a wild row's wake: the rows its dragged filter misses),
            and the pass on that level."""
            first = run(provisional, skip)
            if not first.valid.any():
                raise nothing_valid_error(
                    problem, data, first.reason, buckets.dtype, "noise estimation"
                )
            noise = _noise(first, skip, settled, floor, X84)[0]
            return noise, run(noise, skip)

        noise, first = level(none)
    else:
        noise, first = problem.noise_std, run(problem.noise_std, none)
        if not first.valid.any():  # the method's own run reports it (or copes)
            return Screen(problem, none, _flag(first, np.inf, True), ())
    candidates = _flag(first, threshold, not estimate)
    wild = np.abs(candidates.z) > threshold  # nan (not judged) is not wild
    stuck = [r for r in runs if wild[r.rows, r.output].any()]
    if stuck:
        return _without_runs(data, stuck)
    last, found = first, candidates
    if candidates.mask.any():  # judged again with the candidates skipped
        last = run(noise, candidates.mask)
        again = _flag(last, threshold, not estimate)
        # only candidates: a row that looks wild only once its neighbours are
        # skipped belongs to a change the filter must follow, not to a reading
        found = again._replace(mask=again.mask & candidates.mask)
    if not estimate:
        notes = _given_noise_note(problem, last)
    else:
        notes = ()
        if found.mask.any() and not np.array_equal(found.mask, candidates.mask):
            # the noise from a pass that skips the outliers and no other row (the
            # level it runs on matters little: R = var(nu) (2 - k) / 2 holds for
            # any noise a pass assumes)
            last = run(noise, found.mask)
        noise, counts = _noise(last, found.mask, settled, floor, threshold)
        notes = _few_rows_note(problem.output_names, counts, noise)
        source = (
            "estimated (one-step innovations of a UKF pass, corrected for the "
            "share the update absorbs; outliers left out)"
        )
        problem = problem.with_noise(noise, source)
    if found.mask.any():  # the outputs' centre of the rows used, as without them
        x_mean = np.nanmean(data.x[~found.mask], axis=0)  # a partial row has NaN
        x_mean = x_mean.astype(problem.norm.x_mean.dtype)
        norm = problem.norm._replace(x_mean=x_mean)
        problem = dataclasses.replace(problem, norm=norm)
    return Screen(problem, found.mask, found, notes, last.z, last.valid)


def _pass_function(problem: Problem, data: Dataset, cfg: UKF, dtype):
    """``(noise [S], w, x, mask, probe) -> (reason, xhat, innovation, its std)`` of
    the UKF on ``problem`` with that noise, ``[U, T, ...]``, the ``probe`` rows
    judged though skipped: the method table's UKF program
    (:func:`~jaxcal.calibrators.methods.ukf.ukf_program`, compiled once per process; the
    noise and the outputs' centre are arguments)."""
    # the outputs' median: a mean a wild reading moved (1e6 in one row) would cost
    # every unit digits in float32
    centre = np.nan_to_num(robust_centre(data.x))
    inputs = model_inputs(problem, cfg, dtype, x_mean=centre)
    program = ukf_program(problem, cfg, dtype)

    def run(noise, w, x, mask, probe):
        inp = inputs._replace(noise_std=noise)
        out, innovation, std = program(inp, w, x, mask, probe)
        return out.reason, out.xhat, innovation, std

    return run


def _pass(
    ukf, noise, skip: np.ndarray, *, data: Dataset, buckets: Buckets, r: float
) -> _Pass:
    """The UKF with ``noise`` over every group skipping ``skip [N]``, judged at
    every row (the filter's measurement std ``r * noise``)."""
    groups = []  # (reason, xhat, innovation, its std) of each group
    noise = jnp.asarray(noise, buckets.dtype)
    for part, skip_part in zip(
        buckets.parts, buckets.from_rows(skip, False), strict=True
    ):
        mask, probe = part.mask & ~skip_part, part.mask & skip_part
        out = ukf(noise, jnp.asarray(part.w), jnp.asarray(part.x), mask, probe)
        groups.append([np.asarray(v) for v in out])
    reason, _, innovation, spread = (
        buckets.to_rows(values, MASKED if k == 0 else np.nan)
        for k, values in enumerate(zip(*groups, strict=True))
    )
    valid = reason == OK
    observed = np.isfinite(data.x)  # a missing output's innovation is a 0
    with np.errstate(all="ignore"):
        z = innovation / spread
        absorbed = np.where(observed, 1.0 - r**2 / spread**2, np.nan)
    return _Pass(
        z=z, innovation=np.where(observed, innovation * np.asarray(noise), np.nan),
        absorbed=absorbed, valid=valid,
        judged=valid | (skip & (reason == MASKED)), reason=reason, skip=skip,
    )  # fmt: skip


def _flag(run: _Pass, threshold: float, given: bool) -> OutlierRows:
    """The rows beyond the gate: the standardised innovations over their robust
    centre and scale (a model misfit shifts and widens them all: that is not an
    outlier); with a ``given`` noise the scale is at least 1, so a row is judged
    against that noise or the data's own spread, whichever is wider."""
    centre = np.nan_to_num(robust_centre(run.z, run.judged))
    scale = np.nan_to_num(robust_scale(run.z, run.judged))
    scale = np.maximum(scale, 1.0) if given else np.where(scale > 0, scale, 1.0)
    return outlier_rows((run.z - centre) / scale, 1.0, run.judged, threshold)


def _noise(run: _Pass, flagged, settled, floor, threshold):
    """``([S] noise std, [S] readings it rests on)`` from a pass's one-step
    innovations, rows beyond ``threshold`` robust scales rejected, corrected for the
    share ``k`` the update absorbs: ``R = var(nu) (2 - k) / 2`` (module
    docstring)."""
    keep = run.valid & ~flagged & settled
    if keep.sum() < 2:
        keep = run.valid & ~flagged
    if keep.sum() < 2:
        raise ValueError(
            f"cannot estimate the noise: only {int(keep.sum())} of "
            f"{len(keep)} rows could be used (result.reason of a run with noise= "
            "says why the others were skipped); give noise="
        )
    var = robust_noise(run.innovation, keep, threshold) ** 2
    with warnings.catch_warnings():  # an output never observed: nan, floored
        warnings.simplefilter("ignore", RuntimeWarning)
        k = np.nanmean(np.where(keep[:, None], run.absorbed, np.nan), axis=0)
    std = np.sqrt(var * (2.0 - np.clip(k, 0.0, 1.0)) / 2.0)
    counts = np.sum(keep[:, None] & np.isfinite(run.innovation), axis=0)
    return np.maximum(np.nan_to_num(std), floor), counts


def _few_rows_note(names, counts, noise) -> tuple[str, ...]:
    """A note where an output's noise rests on fewer than :data:`MIN_NOISE_ROWS`
    readings (module docstring)."""
    few = counts < MIN_NOISE_ROWS
    if not few.any():
        return ()
    listed = ", ".join(
        f"{n} ({int(c)} rows: {s:.3g})"
        for n, c, s, f in zip(names, counts, noise, few, strict=True)
        if f
    )
    return (
        f"the noise was estimated from too few rows on {listed}, fewer than "
        f"{MIN_NOISE_ROWS} settled rows per output: it can be off by orders of "
        "magnitude, and the std and outlier flags with it; give noise={output: "
        "std} (e.g. from the sensors' data sheets)",
    )


def _without_runs(data: Dataset, runs: list[StuckRun]) -> tuple[Dataset, tuple]:
    """``(data, notes)``: the rows with the readings of the stuck ``runs`` left
    out (``nan``: the rows become partial) and a note naming each."""
    x = np.array(data.x, copy=True)
    lines = []
    for run in runs:
        x[run.rows, run.output] = np.nan
        times = data.time[run.rows]
        lines.append(
            f"{data.output_names[run.output]} of unit {run.unit} reads "
            f"{data.x[run.rows[0], run.output]:.6g} on {len(run.rows)} rows in a "
            f"row (time {times.min():g} to {times.max():g})"
        )
    note = (
        "a stuck sensor: " + "; ".join(lines[:5]) + ("; ..." if len(lines) > 5 else "")
        + ", a constant reading the model does not follow. Those readings are left "
        "out (the rows are partial, used on their other outputs; result.partial)"
    )  # fmt: skip
    return dataclasses.replace(data, x=x), (note,)


def _settled(buckets: Buckets) -> np.ndarray:
    """``[N]`` rows past each unit's first :data:`SETTLE` share."""
    parts = [
        np.arange(p.mask.shape[1])[None] >= SETTLE * p.lengths[:, None]
        for p in buckets.parts
    ]
    return buckets.to_rows(parts, False)


def _given_noise_note(problem: Problem, run: _Pass) -> tuple[str, ...]:
    """A note when the innovations are far wider than the given noise predicts."""
    typical = np.nan_to_num(robust_scale(run.z, run.judged))
    wide = typical > WIDE_INNOVATIONS
    if not wide.any():
        return ()
    listed = ", ".join(
        f"{name} (noise {s:.3g}: {t:.3g} x)"
        for name, s, t, w in zip(
            problem.output_names, problem.noise_std, typical, wide, strict=True
        )
        if w
    )
    return (
        f"the innovations are typically wider than the noise given predicts on "
        f"{listed}: the noise is too small or the model misfits; outliers were "
        "judged against the innovations' own spread there",
    )
