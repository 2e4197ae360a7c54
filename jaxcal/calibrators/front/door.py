"""The front door: ``jaxcal.calibrate(model, data, method=...)``.

One call calibrates any :class:`~jaxcal.model.Model` on any data source with any
method, each unit as its own stream (``lax.scan`` over time, ``vmap`` over units,
jitted), and returns per-row results in the input's row order::

    result = jaxcal.calibrate(model, "data.csv", method="ukf")
    result.theta        # [N, P] numpy, result.theta_names
    result.theta_std    # [N, P] (UKF; None where a method has no uncertainty)
    result.valid        # [N] bool: False where a sample was skipped, result.reason
    result.partial      # [N] bool: some outputs of the row were missing (NaN)
    result.misfit       # [N] bool: the unit's innovations coloured: std not honest

Methods (peers under the one ``Calibrator(init, step)`` interface): every method of
the registry (:mod:`jaxcal.calibrators.methods`; each its package's docstring), among
them

* ``"ukf"``: the unscented Kalman filter on the model (random-walk parameters);
* ``"ls"``: sliding-window least squares on the model (Levenberg–Marquardt);
* ``"e2e"``: a network ``theta_t = G(w_t, x_t, x_{t-1})`` trained on simulations of
  the model over the parameter box (or pass trained weights as ``e2e=``);
* ``"policy"``: a trained tracking policy, ``run=<run folder>``; an incremental
  (feedback) policy's run with ``anchor=<absolute policy's run folder>`` is gated by
  it where the model misfits the data (:mod:`jaxcal.calibrators.methods.policy.gated`).

A model with hidden states (``Model.from_step``) takes the same call: the UKF
filters the states jointly with the parameters, least squares fits the parameters
and the window's initial state by simulating the model over a sliding window, E2E
reads a window of past samples, a policy carries the model state;
``result.states [N, Z]`` holds the estimated states where a method has them.

Partial rows: a row with some outputs missing (NaN or an empty cell; conditions
finite, at least one output finite) is read and kept. The UKF and least squares
update on its observed outputs (``valid`` True, ``reason`` ``ok``); E2E and a policy
cannot take a NaN input and skip it (``valid`` False, ``reason`` ``x_partial``).
Either way ``result.partial`` marks it: a flag of its own, not a reason, so that
``reason != "ok"`` still means "skipped" everywhere. Its ``xhat`` holds the model's
prediction of the missing outputs.

Noise: ``noise={output: std}``; when omitted it is estimated from the data, robustly,
from the one-step innovations of UKF passes (:mod:`jaxcal.calibrators.front.screen`;
``result.noise_source`` says so). A reported ``theta_std`` is never below the
estimate's own row-to-row scatter (:mod:`jaxcal.calibrators.uncertainty.jitter_check`).
Where the screening pass's one-step innovations are clearly autocorrelated the
unit's std, which assumes white noise, is withheld (NaN; ``misfit="keep"`` reports it
anyway), ``result.misfit`` marks those units' rows and a note says why
(:mod:`jaxcal.calibrators.uncertainty.misfit_check`; not checked without a screening
pass).

No single bad row decides anything for the other rows:

* **Outliers.** The same UKF passes flag wild readings (an innovation beyond
  ``outlier_z`` = 6 robust stds, :mod:`jaxcal.calibrators.front.screen`): they are
  skipped by every method, left out of the noise, and reported as ``reason ==
  "outlier"``. With a given noise they are judged against that noise (or the data's
  own spread where wider). ``outlier_z=None`` turns the flags off; the policy
  without ``noise=`` is not screened (nothing to judge by).
* **Skipped rows** (flagged for any reason) report the estimate carried from the
  unit's last used row, or before its first one the prior (``theta`` the nominal
  values, ``theta_std`` the UKF's prior std or a uniform's over the box, ``xhat``
  ``nan``), with ``valid`` False. Every flag is counted on one console line (a
  ``UserWarning``, also in ``result.notes``); a calibration that keeps no row is an
  error that says why (:mod:`jaxcal.calibrators.front.rows`).
* **Bounds.** Every method's ``theta`` lies inside the declared box: the UKF's mean
  and least squares' steps are projected onto it, any other method's estimate is
  clipped, and the rows whose estimate reached a bound are marked
  (``result.at_bound``) and named in a note (:mod:`jaxcal.calibrators.front.rows`).
* **Memory** grows with the rows: units are padded in groups of similar length
  (:mod:`jaxcal.data.buckets`), one compiled program per group shape.

Compiled once: the UKF and least squares are compiled once per process and method
settings (:mod:`jaxcal.calibrators.programs.compiled`) and once per machine through
JAX's persistent compilation cache (:mod:`jaxcal.cache`; ``JAXCAL_CACHE=0`` turns
it off); the screening once per data set in a process
(:mod:`jaxcal.calibrators.front.screen_memo`); a changed global of a user's model
builds new programs (:mod:`jaxcal.calibrators.programs.traced_key`).

The result in the data's row order is assembled by :mod:`jaxcal.calibrators.front.
rows`. A parameter that acts in some units only (``model.diagnosis.carriers``) is
calibrated in its carriers and held at its nominal value elsewhere
(:mod:`jaxcal.calibrators.front.carriers`).
"""

from __future__ import annotations

import dataclasses
import sys
import warnings
from collections.abc import Mapping, Sequence

import numpy as np

from jaxcal import cache
from jaxcal.calibrators import methods
from jaxcal.calibrators.front import carriers, screen_memo
from jaxcal.calibrators.front.outliers import OUTLIER_Z
from jaxcal.calibrators.front.result import CalibrationResult
from jaxcal.calibrators.front.rows import flag_notes, nothing_valid_error, to_rows
from jaxcal.calibrators.guard import REASON_CODE
from jaxcal.calibrators.programs import traced_key
from jaxcal.calibrators.uncertainty.jitter_check import jitter_floor, jitter_note
from jaxcal.calibrators.uncertainty.misfit_check import (
    colour_rows,
    misfit_note,
    widen_note,
    widening,
)
from jaxcal.data.buckets import bucket_units
from jaxcal.data.dataset import clip_jitter
from jaxcal.data.readers import read_dataset
from jaxcal.model import Model
from jaxcal.models import load
from jaxcal.precision import is_x64, require_x64
from jaxcal.problem import Problem
from jaxcal.progress import progress_bar

_READER_OPTIONS = ("rename", "ignore", "nonfinite")
METHODS = tuple(methods.METHODS)  # the method table's names
PROGRESS_AFTER = 3.0  # seconds before a call shows its progress line
# A coloured unit's std: withheld (NaN, the default) or kept with its rows marked.
MISFIT = ("withhold", "keep")


def _dtype(model: Model):
    if model.x64:
        require_x64(f"model {model.name!r} needs float64 (an iterative solver inside)")
    return np.float64 if is_x64() else np.float32


def calibrate(
    model: Model | str,
    data,
    method: str = "ukf",
    theta: Sequence[str] | None = None,
    noise: Mapping[str, float] | float | None = None,
    *,
    outputs: Sequence[str] | None = None,
    seed: int = 0,
    progress: bool = True,
    **options,
) -> CalibrationResult:
    """Calibrate ``model`` on ``data`` with ``method`` (see the module docstring).

    Args:
        model: a :class:`~jaxcal.model.Model` or a ``jaxcal.models.load`` spec.
        data: a path (.csv/.parquet/.h5/.txt), a pandas DataFrame or a
            :class:`~jaxcal.data.dataset.Dataset`.
        method: one of :data:`METHODS`.
        theta: calibrated parameter names (default: all the model's).
        noise: output name -> noise standard deviation, or one number for every
            output (default: estimated).
        outputs: outputs to use (default: every model output in the data).
        seed: PRNG seed (E2E training).
        progress: show a progress line on stderr when the call takes longer than
            :data:`PROGRESS_AFTER` seconds (``False``: never).
        options: method settings — ``q``, ``prior_std`` (UKF), ``window``,
            ``num_iters`` (LS), ``e2e``/``e2e_config``/``e2e_window`` (E2E), ``run``
            (policy); for a model with hidden states ``state_std`` (initial-state
            std: scalar, ``[Z]`` or ``{state: std}``; default 1 % of the state's
            size) and ``state_q`` (UKF process noise on the states per step,
            default 1e-6 of the state's size: the model is trusted);
            ``outlier_z`` (the outlier gate in robust stds, default 6; ``None``:
            no outlier flags); ``misfit`` (``"withhold"``, the default: no std for
            a unit whose innovations are coloured; ``"keep"``: report it, rows
            marked); and the readers' ``rename``, ``ignore``, ``nonfinite``.

    Returns:
        :class:`CalibrationResult`.

    Raises:
        ValueError: unknown method or option, names that do not match the model,
            a given noise std outside the float dtype's range (``1e-300`` in
            float32), bad data (naming file, column and rows), no row that could be
            used (with the cause: the input checks, the model's non-finite outputs, a
            noise too small for the arithmetic).
    """
    methods.get(method)  # an unknown name: the registered ones listed
    cache.ensure_default()  # compile once per machine (jaxcal.cache)

    model = load(model)
    dtype = _dtype(model)
    if model.origin is None:  # a user's function may read a global changed since
        traced_key.refresh(model, dtype)  # new programs if it did
    theta = _names(theta, "theta", "parameter", model.parameter_names)
    outputs = _names(outputs, "outputs", "output", model.output_names)
    if carriers.applies(model, theta, method, options):  # some units only: per group
        result, data = carriers.calibrate_split(
            calibrate, model, data, method, theta, noise, outputs=outputs, seed=seed,
            progress=progress, options=options,
        )  # fmt: skip
        if result is not None:
            return result
    misfit = _misfit(options.pop("misfit", "withhold"))
    cfg, data, problem, notes, threshold = _read_problem(
        model, data, method, theta, noise, outputs, options, dtype
    )
    buckets = bucket_units(data, dtype)
    bar = _progress(len(buckets.parts) + 2, progress)
    screened, problem, built = _screen_and_build(
        cfg, problem, data, buckets, noise, threshold, seed, bar
    )
    if screened is not None and screened.data is not None:  # a stuck sensor's
        data, buckets = screened.data, screened.buckets  # readings left out
    skip = np.zeros(data.num_rows, bool) if screened is None else screened.outlier
    outs = _run_groups(built, buckets, skip, method, bar)
    result = to_rows(outs, buckets, data, problem, method, built.prior_std, skip)
    if not result.valid.any():
        codes = np.asarray([REASON_CODE[r] for r in result.reason])
        raise nothing_valid_error(problem, data, codes, dtype, "calibrate")
    flagged = flag_notes(result, problem, data, screened, dtype)
    flagged += [] if screened is None else list(screened.notes)
    result, checked = _checked_std(result, screened, problem, misfit)
    flagged += checked
    for line in flagged:  # the console line (a warning: shown once per message)
        warnings.warn(f"jaxcal.calibrate: {line}", stacklevel=2)
    return dataclasses.replace(result, notes=(*notes, *flagged))


def _checked_std(result: CalibrationResult, screened, problem: Problem, misfit: str):
    """``(result, notes)``: a reported std never below the estimate's own scatter
    (:mod:`.jitter_check`), and the units whose innovations are clearly coloured
    or shifted marked in ``result.misfit`` (:mod:`.misfit_check`; where a screening
    ran), their std withheld (NaN) unless ``misfit == "keep"``; a unit whose noise is
    coloured, not misfitting, has its std widened by the colour's long-run variance."""
    if result.theta_std is None:
        return result, []
    std, factor = jitter_floor(
        result.unit, result.time, result.theta, result.theta_std, result.valid
    )
    result = dataclasses.replace(result, theta_std=std)
    notes = jitter_note(factor, result.unit, problem.theta_names)
    if screened is not None and screened.z is not None:  # the innovations' colour
        colour = colour_rows(result.unit, result.time, screened.z, screened.used)
        rows, kept = colour.misfit, misfit == "keep"
        # a coloured noise: fewer rows' worth
        widen = widening(colour, methods.get(result.method).white_std)
        std = std * widen[:, None]
        std = std if kept else np.where(rows[:, None], np.nan, std)
        result = dataclasses.replace(result, misfit=rows, theta_std=std)
        notes += misfit_note(
            colour.ratio, result.unit, problem.output_names, withheld=not kept,
            shift=colour.shift,
        )  # fmt: skip
        notes += widen_note(widen, result.unit)
    return result, notes


def _read_problem(model: Model, data, method, theta, noise, outputs, options, dtype):
    """``(cfg, data, problem, notes, threshold)`` of a call: the method's config
    from ``options`` (the readers' options and ``outlier_z`` taken out of it; a
    policy's ``run`` loaded, its names the defaults), the data read for the model
    (conditions clipped to its range where within jitter: ``notes``), the problem
    and its noise checked against the float dtype."""
    reader = {k: options.pop(k) for k in _READER_OPTIONS if k in options}
    threshold = _threshold(options.pop("outlier_z", OUTLIER_Z))
    # a trained policy fixes its parameters and outputs: its run's are the defaults
    options, theta, outputs = methods.get(method).prepare(options, theta, outputs)
    cfg = methods.config(method, options)
    data = read_dataset(data, model, **reader).for_model(model, outputs)
    clipped, notes = clip_jitter(data.w, model)
    data = dataclasses.replace(data, w=clipped)
    noise = _noise_per_output(noise, data.output_names)
    problem = Problem.build(model, data, theta=theta, noise=noise)
    _check_noise_precision(problem, dtype)
    return cfg, data, problem, notes, threshold


def _screen_and_build(cfg, problem, data, buckets, noise, threshold, seed, bar):
    """``(screened, problem, built)``: the screening passes (:func:`_screen`; their
    noise goes into the problem), then the method built on the screened problem,
    each a step of the progress ``bar``."""
    bar.set_description_str("jaxcal.calibrate: screening (UKF passes)", False)
    screened = _screen(cfg, problem, data, buckets, noise, threshold)
    if screened is not None:
        problem = screened.problem
        buckets = screened.buckets or buckets  # a stuck sensor's readings left out
    bar.update()
    bar.set_description_str(f"jaxcal.calibrate: building {cfg.name}", False)
    built = methods.build(problem, cfg, buckets, seed)
    bar.update()
    return screened, problem, built


def _run_groups(built, buckets, skip: np.ndarray, method: str, bar) -> list:
    """The built method's output on each padded unit group (``skip [N]`` rows, the
    outliers, skipped like padding), a step of the progress ``bar`` each."""
    parts = zip(buckets.parts, buckets.from_rows(skip, False), strict=True)
    outs = []
    for k, (part, cells) in enumerate(parts):
        bar.set_description_str(f"jaxcal.calibrate: {method}, unit group {k + 1}", 0)
        outs.append(built.run(part, cells))
        bar.update()
    bar.close()
    return outs


def _progress(total: int, enabled: bool):
    """A progress line on stderr, shown only once a call has taken
    :data:`PROGRESS_AFTER` seconds (a first call compiles; E2E trains; the
    turbofan's filter passes take seconds each); in a log file, a line per stage
    (:mod:`jaxcal.progress`)."""
    return progress_bar(
        total=total, desc="jaxcal.calibrate", delay=PROGRESS_AFTER, leave=False,
        disable=not enabled, file=sys.stderr,
        bar_format="{desc} ({n}/{total} steps, {elapsed})",
    )  # fmt: skip


def _noise_per_output(noise, names: Sequence[str]):
    """``noise`` as ``{output: std}``: one number is every used output's std (as
    ``noise=0.02`` on the command line); a mapping or a sequence passes through.

    Raises:
        ValueError: a number that is not finite and > 0.
    """
    if isinstance(noise, Mapping) or (
        not isinstance(noise, int | float | np.number) and np.ndim(noise) != 0
    ):  # np.ndim of a dict is 0: a mapping is told apart first
        return noise  # a mapping or one std per output (None: estimated)
    if noise is None or isinstance(noise, bool | str):
        return noise  # None: estimated; True or "0.1": refused by Problem.build
    std = float(noise)
    if not (np.isfinite(std) and std > 0):
        raise ValueError(
            f"noise={noise!r}: expected a finite std > 0 (one number for every "
            "output, or {output: std})"
        )
    return dict.fromkeys(names, std)


def _check_noise_precision(problem: Problem, dtype) -> None:
    """A given noise std must be a normal positive number in the calibration's
    float dtype: ``1e-300`` is 0 in float32 (x64 off), ``1e300`` is inf, and XLA
    flushes subnormals to 0; the filter's normalisation would then fail with a
    message naming nothing of the user's.

    Raises:
        ValueError: naming the outputs, their std and the dtype's range.
    """
    info = np.finfo(dtype)
    with np.errstate(over="ignore"):  # 1e300 -> inf in float32: that is the check
        cast = np.asarray(problem.noise_std, np.float64).astype(dtype)
    bad = ~(np.isfinite(cast) & (cast >= info.tiny))
    if not bad.any():
        return
    stds = zip(problem.output_names, problem.noise_std, bad, strict=True)
    shown = ", ".join(f"{name}={std:.3g}" for name, std, b in stds if b)
    raise ValueError(
        f"noise: the std of {shown} is outside the range of {info.dtype.name}, the "
        f"precision this calibration runs in (a std from {info.tiny:.3g} to "
        f"{info.max:.3g}): give the std in the outputs' units, or enable float64 "
        "(jaxcal.precision.enable_x64()) if so small or large a noise is meant"
    )


def _names(value, field: str, kind: str, declared: Sequence[str]):
    """``theta`` / ``outputs``: ``None`` (the default) or a non-empty list of names.
    An empty list is refused rather than read as "all" (a filter that selected
    nothing would otherwise calibrate every parameter), and a bare string rather
    than read letter by letter.

    Raises:
        ValueError: naming the option, the expected form and the model's names.
    """
    if value is None:
        return None
    example = f"{field}=[{declared[0]!r}]" if declared else f"{field}=[...]"
    if isinstance(value, str):
        raise ValueError(
            f"{field} must be a list of {kind} names, got the string {value!r}: "
            f"write {field}=[{value!r}] (the model's {kind}s are {list(declared)})"
        )
    try:
        names = list(value)
    except TypeError:
        names = None
    if names is None or not all(isinstance(n, str) for n in names):
        raise ValueError(
            f"{field} must be a list of {kind} names (e.g. {example}), got {value!r}"
        )
    if not names:
        raise ValueError(
            f"{field}=[] names no {kind}: give at least one of {list(declared)}, or "
            f"leave {field} out (None) for all of them"
        )
    return names


def _misfit(value) -> str:
    """The ``misfit`` option, checked: what a coloured unit's std becomes."""
    if value not in MISFIT:
        raise ValueError(f"misfit must be one of {MISFIT}, got {value!r}")
    return value


def _threshold(value) -> float:
    """``outlier_z``: a positive number (``None`` or ``inf``: flag no outliers)."""
    value = np.inf if value is None else value
    try:
        value = float(value)
    except (TypeError, ValueError):
        value = np.nan
    if not value > 0:
        raise ValueError(
            f"outlier_z must be a number > 0 (or None: no outlier flags), got {value!r}"
        )
    return value


def _screen(cfg, problem, data, buckets, noise, threshold):
    """The noise (estimated when not given) and the outlier rows (:mod:`.screen`),
    or ``None`` where there is nothing to screen by: a policy without a noise
    level, or a given noise with outlier flags off. The passes are the method's own
    UKF, else a default one with the method's state settings; the same rows and
    settings are screened once per process (:mod:`.screen_memo`)."""
    method = methods.method_of(cfg)
    if noise is None and not method.reads_noise:
        return None
    if noise is not None and threshold == np.inf:
        return None
    cfg = method.screening(cfg)
    # once per data set in a process (a second method reuses it)
    return screen_memo.screened(
        problem, data, buckets, cfg, estimate=noise is None, threshold=threshold
    )
