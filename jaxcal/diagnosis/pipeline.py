"""Close the loop on one data set: calibrate, trace the residual, add the effect.

:func:`diagnose` runs the steps of design/loop.md on any :class:`~jaxcal.model.Model`
and a :class:`~jaxcal.data.dataset.Dataset` (time = cycle). A model with memory is
fitted in **output-error** form: each unit is simulated from its initial state (with an
offset fitted per unit) and every candidate acts through the states
(:mod:`jaxcal.diagnosis.kinds.signatures`).

1. **Calibrate** the declared parameters (per-unit splines in time, jointly over
   the data): the "before" model.
2. **Noise.** The noise model (:mod:`jaxcal.diagnosis.residuals.noise`: a level and
   an AR(p) colour per output, or the given levels and an estimated colour) is
   fitted to this fit's residual, quantised outputs are dropped and the fit is
   repeated on the prewhitened residual.
3. **Trace** the prewhitened residual to the library
   (:func:`jaxcal.diagnosis.fitting.identify.identify`: every kind in its fleet-wide
   and per-unit forms, steps with their onsets). The noise model is then fitted
   again to the winner's residual (an effect left in the residual inflates the
   estimated colour and level) and the trace repeated when it changed by more than
   :data:`NOISE_SETTLED` (an iteration of Cochrane & Orcutt 1949; each refit starts
   where the last pass's ended); without a winner, to the best candidate's residual,
   and the trace repeated when that lowered a level by more than :data:`LEVEL_MOVE`
   (a misfit read as noise hides every candidate).
4. **Fallback.** A cross-validated ``delta(w)`` is fitted to the residual of the best
   model so far (:mod:`jaxcal.diagnosis.fitting.discrepancy`, generalised least
   squares). If it is significant, the declared parameters and delta are fitted by
   backfitting, the library is screened again against that model, and an effect is
   kept only if it is still significant beyond delta; a library effect that explains
   the residual better than delta alone (BIC with delta's degrees of freedom
   counted) is kept.
5. **Add** the chosen effect(s), refit, and report the errors before and after:
   tracking RMSE per output, theta RMSE where the truth is known and the whiteness of
   the prewhitened residual.
6. **Per unit and plausibility.** Each added effect gets its size, carriers and onset
   per unit (:mod:`jaxcal.diagnosis.report.units`), and the final fit is checked
   against the model's bounds and direction of wear
   (:mod:`jaxcal.diagnosis.report.plausibility`); triggered checks are flags.

Verdicts: ``none`` (nothing found), ``identified``, ``confounded``
(the winner shares its signature with others within the BIC margin; the set is
reported, the winner stands in for it in the "after" model), ``discrepancy`` (delta
only) and ``identified+discrepancy`` / ``confounded+discrepancy``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from threadpoolctl import threadpool_limits

from jaxcal.calibrators.front.outliers import OUTLIER_Z
from jaxcal.data.dataset import Dataset
from jaxcal.diagnosis.data.cleaning import drop_outliers
from jaxcal.diagnosis.data.prepare import LoopData, prepare_data
from jaxcal.diagnosis.fitting.discrepancy import Discrepancy, DiscrepancyConfig
from jaxcal.diagnosis.fitting.fallback import fallback
from jaxcal.diagnosis.fitting.identify import (
    Identification,
    IdentifyConfig,
    identify,
    warm_starts,
)
from jaxcal.diagnosis.fitting.joint import FitResult, fit_model, raw_columns_of
from jaxcal.diagnosis.fitting.ranking import effect_sizes
from jaxcal.diagnosis.fitting.screen import init_from, spec_for
from jaxcal.diagnosis.kinds.table import Candidate, build_library
from jaxcal.diagnosis.kinds.terms import ModelSpec
from jaxcal.diagnosis.report.extended import extended_model
from jaxcal.diagnosis.report.plausibility import plausibility_flags
from jaxcal.diagnosis.report.units import fleet_summary, unit_effects, unit_trajectories
from jaxcal.diagnosis.residuals.noise import MAX_ORDER, ljung_box_p
from jaxcal.diagnosis.residuals.noise_fit import fit_noise, quantised
from jaxcal.diagnosis.residuals.summaries import ResidualSummary, summarize_residuals
from jaxcal.diagnosis.timing import StageClock
from jaxcal.model import Model
from jaxcal.models import load

NOISE_ROUNDS = 2  # noise model <-> declared-only fit alternations
LEVEL_MOVE = 1.25  # a best candidate that lowers a noise level this much: retrace
# a refitted noise model this close to the one in use (relative level and inflation,
# AR coefficients; the same orders) has not changed: the trace is not repeated
NOISE_SETTLED = 0.01
# BLAS threads of the host algebra. Its products are small and per unit (a unit's
# Gram blocks, its projections); OpenBLAS threads that spin beside JAX's own pool
# on a loaded machine make them many times slower.
BLAS_THREADS = 1
# the stages timed in DiagnosisResult.timings / report.json (.timing), in run order
STAGES = (
    "prepare", "calibrate", "outliers", "noise", "screen", "noise passes",
    "fallback", "per unit",
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Static settings of the diagnosis."""

    knots: int = 6  # B-spline functions per unit for each declared parameter
    candidate_knots: int = 3  # ... for each candidate (undeclared) parameter
    kinds: tuple[str, ...] = ()  # restrict the library (empty: every kind, .kinds)
    identify: IdentifyConfig = IdentifyConfig()
    discrepancy: DiscrepancyConfig = DiscrepancyConfig()
    max_lag: int = 10  # autocorrelation lags / Ljung–Box h
    max_iters: int = 20  # Levenberg–Marquardt iterations of the declared-only fit
    outlier_z: float | None = OUTLIER_Z  # a wild reading (None: keep every row)
    noise_order: int = MAX_ORDER  # highest AR order of the noise (0: white noise)
    noise_passes: int = 3  # noise model refitted to the best candidate's residual


class Stage(NamedTuple):
    """A calibrated model and its errors ("before" or "after")."""

    fit: FitResult
    offset: np.ndarray | None  # [N, S] discrepancy term, output units
    summary: ResidualSummary
    tracking_rmse: np.ndarray  # [S] output units
    tracking_rmse_norm: np.ndarray  # [S] multiples of the noise std
    theta_rmse: dict  # parameter -> RMSE against the truth (empty without truth)
    whiteness: float  # share of outputs whose prewhitened residual passes Ljung–Box
    whiteness_p: np.ndarray  # [S] Ljung–Box p of the prewhitened residual


class DiagnosisResult(NamedTuple):
    """Everything :mod:`jaxcal.diagnosis.report.write` writes."""

    data: LoopData
    model: Model
    declared: tuple[str, ...]
    library: tuple[Candidate, ...]
    identification: Identification  # the library against the declared-only residual
    rescreen: Identification | None  # again, against declared + delta (when delta fits)
    verdict: str
    identified: list  # dicts: name, kind, form, size, std, unit (the added effects)
    confounded: list  # names, when the verdict is "confounded"
    discrepancy: Discrepancy | None  # significant delta(w), or None
    before: Stage
    after: Stage
    added: list  # names of the model terms added for "after"
    members: tuple = ()  # the added library effects (Candidates, in their forms)
    unit_effects: tuple = ()  # units.UnitEffect per added library effect
    flags: tuple = ()  # plausibility flags (dicts, plausibility.FLAGS)
    fallback_note: str = ""  # what the fallback kept or dropped, and why
    alpha: float = 0.01  # level of the per-unit test and bands
    timings: dict = {}  # stage -> wall seconds, and "total" (.timing)

    @property
    def extended_model(self):
        """The model with every added effect as a parameter."""
        return extended_model(self)


def make_stage(
    data: LoopData, fit: FitResult, offset, max_lag: int, theta_names=()
) -> Stage:
    """Errors of a fitted model on the entries where it is valid and observed.

    ``theta_rmse`` covers the fitted parameters and ``theta_names`` that have a true
    value in the data (a parameter the model does not fit is held at its nominal
    value, so its RMSE is the size of its departure).
    """
    ev = fit.evaluation
    valid, used = ev.valid, ev.used
    err = np.where(used, ev.resid * data.noise_std, np.nan)
    theta_rmse = {}
    if data.theta_true is not None:
        names = list(fit.spec.unit_params)
        names += [n for n in theta_names if n not in names]
        for name in names:
            if name not in data.theta_names:
                continue
            j = data.parameter_names.index(name)
            t = data.theta_names.index(name)
            diff = ev.theta[valid, j] - data.theta_true[valid, t]
            theta_rmse[name] = float(np.sqrt(np.mean(diff**2)))
    summary = summarize_residuals(
        ev.resid, data.w, data.cycle, data.starts,
        max_lag=min(max_lag, data.num_rows - 1),
    )  # fmt: skip
    white_p = ljung_box_p(ev.white, max_lag)
    return Stage(
        fit,
        offset,
        summary,
        np.sqrt(np.nanmean(err**2, axis=0)),
        np.sqrt(np.nanmean(np.where(used, ev.resid, np.nan) ** 2, axis=0)),
        theta_rmse,
        float(np.mean(white_p > 0.01)),
        white_p,
    )


def _effects_of(members, fit: FitResult, data) -> list:
    sizes, stds = effect_sizes(fit, members, data)
    return [
        {
            "name": c.name,
            "kind": c.kind.study_kind(c.target),
            "family": c.family,
            "form": c.form,
            "target": c.target,
            "size": s,
            "std": e,
            "unit": c.unit,
        }
        for c, s, e in zip(members, sizes, stds, strict=True)
    ]


def _fit_noise(data: LoopData, fit: FitResult, given, cfg: LoopConfig) -> LoopData:
    """``data`` with the noise model refitted to ``fit``'s residual (quantised
    outputs dropped, with the reason)."""
    ev = fit.evaluation
    raw = np.where(ev.used, ev.resid * data.noise_std, 0.0)
    local = raw_columns_of(ev)[:, :, : fit.layout.num_local]
    cols = np.where(ev.used[:, :, None], local, 0)
    noise = fit_noise(raw, data, sigma=given, max_order=cfg.noise_order, cols=cols,
                      fit=data.noise)  # fmt: skip
    reasons = quantised(data, noise.sigma) if given is None else {}
    if reasons:
        keep = [j for j, s in enumerate(data.sensor_names) if s not in reasons]
        noise = noise.take(keep)
        data = data.drop_sensors(reasons)
    return data.with_noise(noise)


def diagnose(
    data,
    model: Model | str,
    declared: Sequence[str],
    cfg: LoopConfig = LoopConfig(),
    *,
    sensors: Sequence[str] | None = None,
    units: Sequence[int] | None = None,
    max_rows: int | None = None,
    noise_std: Mapping[str, float] | None = None,
    progress: bool = False,
) -> DiagnosisResult:
    """Find the residual, trace it to an effect, add it and compare (module docstring).

    Args:
        data: a :class:`~jaxcal.data.dataset.Dataset` (``time`` = cycle).
        model: a :class:`~jaxcal.model.Model` (static or with hidden states) or a
            ``jaxcal.models.load`` spec; float64 must be enabled by the caller.
        declared: the calibrated (declared) parameters.
        cfg: settings.
        sensors: outputs of the residual (default: all usable).
        units: units to use (default: all).
        max_rows: subsample to about this many rows (a static model).
        noise_std: known marginal noise std by output (default: estimated); the
            colour is estimated either way (``cfg.noise_order``).
        progress: write a progress line per stage and per batch of the fleet's
            rows (stderr, :mod:`.timing`).

    Returns:
        :class:`DiagnosisResult`; ``timings`` holds each stage's wall seconds.
    """
    model, declared = _checked_request(model, declared)
    if not isinstance(data, Dataset):
        raise ValueError(
            "data must be a jaxcal Dataset (a file: "
            f"jaxcal.data.readers.read_dataset), got {type(data)}"
        )
    clock = StageClock(progress)
    try:
        with threadpool_limits(BLAS_THREADS, user_api="blas"):
            res = _run(
                model, data, declared, cfg, clock, sensors=sensors, units=units,
                max_rows=max_rows, noise_std=noise_std, dropped_rows=data.dropped_rows,
            )  # fmt: skip
    finally:
        clock.close()
    return res._replace(timings=clock.timings())


def _run(model, dataset, declared, cfg, clock: StageClock, *, sensors, units,
         max_rows, noise_std, dropped_rows) -> DiagnosisResult:  # fmt: skip
    """The stages of :func:`diagnose`, each timed by ``clock``."""
    with clock.stage("prepare"):
        data = prepare_data(
            dataset, model, sensors=sensors, units=units, max_rows=max_rows,
            knots=cfg.knots, candidate_knots=cfg.candidate_knots,
            noise_std=noise_std, dropped_rows=dropped_rows,
        )  # fmt: skip
    spec0 = ModelSpec(declared, initial_state=model.is_stateful)
    with clock.stage("calibrate"):
        data, null = _valid_rows_fit(model, data, spec0, cfg)
    with clock.stage("outliers"):
        data, null = drop_outliers(model, data, spec0, null, cfg)
    given = None if noise_std is None else data.noise_std
    with clock.stage("noise"):
        for _ in range(NOISE_ROUNDS):  # the fit and its noise model, to a fixed point
            num_s = data.num_sensors
            data = _fit_noise(data, null, given, cfg)
            init = null.params if data.num_sensors == num_s else None
            null = fit_model(model, data, spec0, init, max_iters=cfg.max_iters)
    with clock.stage("screen"):
        library = _library(model, data, declared, cfg)
        ident = identify(model, data, declared, library, cfg.identify, null)
    with clock.stage("noise passes"):
        for _ in range(cfg.noise_passes - 1):
            basis = _noise_basis(model, data, declared, ident, null, cfg)
            if basis is None:
                break
            # the noise refit reads the basis's columns alone; the fits stay as the
            # next pass's warm starts, which read their coefficients and end points
            ident = ident._replace(fits=warm_starts(ident.fits))
            refit = _fit_noise(data, basis, given, cfg)
            del basis
            if refit.num_sensors != data.num_sensors:
                break
            if ident.winner is None and not _level_moved(data.noise, refit.noise):
                break
            if refit.noise.settled(data.noise, NOISE_SETTLED):
                break  # the trace would be repeated under the same noise model
            data, warm, ident = refit, ident.fits, None  # the fits handed over
            null = fit_model(model, data, spec0, null.params, max_iters=cfg.max_iters)
            library = _library(model, data, declared, cfg)
            ident = identify(model, data, declared, library, cfg.identify, null,
                             warm=warm)  # fmt: skip
            del warm
    # the refits were kept for the noise passes alone (a fleet's rows times their
    # columns each): the winner's fit stays
    ident = ident._replace(fits={})
    with clock.stage("fallback"):
        fell_back = fallback(model, data, declared, library, ident, null, cfg)
    with clock.stage("per unit"):
        return _verdicts(model, data, declared, library, ident, null, cfg, fell_back)


def _checked_request(model: Model | str, declared) -> tuple[Model, tuple[str, ...]]:
    """The model (a ``jaxcal.models.load`` spec loaded) and the declared parameters,
    which must be distinct parameters of it."""
    if not isinstance(model, Model):
        model = load(model)
    declared = tuple(declared)
    if not declared or len(set(declared)) != len(declared):
        raise ValueError(f"calibrate must name distinct parameters, got {declared}")
    model.parameter_index(declared)
    return model, declared


def _valid_rows_fit(model: Model, data: LoopData, spec0: ModelSpec, cfg):
    """The declared-only fit, refitted without the rows where the model is invalid
    (masked for a model with memory, whose states run through them): ``(data,
    fit)``."""
    null = fit_model(model, data, spec0, max_iters=cfg.max_iters)
    if not null.evaluation.valid.all():
        bad = int(np.sum(~null.evaluation.valid))
        note = (
            f"{bad} rows left out: the model is invalid there (did not converge or "
            "inputs outside its range)"
        )
        keep = null.evaluation.valid
        data = data.mask_rows(keep, note) if model.is_stateful else data.take_rows(
            keep, note
        )  # fmt: skip
        null = fit_model(model, data, spec0, max_iters=cfg.max_iters)
    return data, null


def _noise_basis(model, data, declared, ident: Identification, null, cfg):
    """The fit the next noise pass estimates the noise on: the winner's, else the
    best fit of a near miss (``None``: no pass is needed)."""
    if ident.winner is not None:
        return _winner_basis(ident, cfg.identify.bic_margin)
    return _best_fit(model, data, declared, ident, null, cfg)


def _winner_basis(ident: Identification, margin: float) -> FitResult:
    """The fit the noise model is refitted to once a winner stands: of the winner
    and the single effects within ``margin`` of its BIC (rivals the criterion does
    not separate from it), the one that leaves the least residual.

    The winner's own residual keeps whatever it misfits, and the noise model reads
    that as a higher level, which keeps the rivals from separating."""
    rivals = [e for e in ident.ranking
              if len(e.members) == 1 and e.name in ident.fits
              and e.bic <= ident.winner.bic + margin]  # fmt: skip
    best = max([ident.winner, *rivals], key=lambda e: e.lr_stat)
    return ident.fits.get(best.name, ident.winner_fit)


def _best_fit(model, data, declared, ident: Identification, null, cfg):
    """The fit of the best candidate, significant or not: the best-ranked one, or the
    near miss (``Identification``) on every unit where its summed score is larger.

    An effect the declared parameters cannot follow leaves a misfit in the
    declared-only residual that the noise model reads as a high level and a strong
    colour, and under that noise no candidate is significant. The best candidate's
    residual is the better basis for the noise. Under so inflated a noise no unit may
    show the effect on its own: the near miss is then the best candidate.
    """
    best = ident.ranking[0] if ident.ranking else None
    if ident.near_miss and (best is None or ident.near_miss[1] > best.lr_stat):
        cand = ident.near_miss[0]
        spec = spec_for(declared, [cand], null.spec.initial_state)
        init = init_from(null, model, data, spec)
        return fit_model(model, data, spec, init, max_iters=cfg.max_iters)
    return None if best is None else ident.fits.get(best.name)


def _level_moved(old, new) -> bool:
    """True when the noise level of some output moved by more than
    :data:`LEVEL_MOVE` (a candidate that explained no misfit changes the level by
    about what it absorbed, which the noise fit gives back)."""
    ratio = np.asarray(old.sigma) / np.maximum(np.asarray(new.sigma), 1e-300)
    return bool(np.any(ratio > LEVEL_MOVE))


def _library(model, data: LoopData, declared, cfg: LoopConfig):
    w_std = data.w.std(0)
    condition_scale = 0.01 * np.where(
        w_std > 0, w_std, np.maximum(np.abs(data.w).mean(0), 1.0)
    )
    mean_abs = np.abs(np.where(data.observed, data.x, np.nan))
    library = build_library(
        model, declared, data.sensor_names, data.noise_std, np.nanmean(mean_abs, 0),
        condition_scale, kinds=cfg.kinds or None,
    )  # fmt: skip
    if not library:
        raise ValueError(
            f"the effect library is empty for kinds {cfg.kinds} with "
            f"calibrate={list(declared)}"
        )
    return library


def _verdicts(model, data, declared, library, ident, null, cfg, fell_back):
    """The verdict, the stages before and after, per-unit verdicts and flags."""
    best, offset, disc, final_ident, rescreen, note = fell_back
    identified, confounded, added, members = [], [], [], []
    if final_ident.winner is not None:
        members = list(final_ident.winner.members)
        identified = _effects_of(members, best, data)
        added = [c.name for c in members]
        confounded = list(final_ident.confounded)
    if disc is not None:
        added.append("discrepancy")
    if final_ident.winner is None:
        verdict = "discrepancy" if disc is not None else "none"
    else:
        verdict = "confounded" if confounded else "identified"
        verdict += "+discrepancy" if disc is not None else ""
    after = make_stage(data, best, offset, cfg.max_lag)
    # theta RMSE "before" also covers the added parameters (held at nominal there)
    before = make_stage(data, null, None, cfg.max_lag, best.spec.unit_params)
    per_unit, flags = _per_unit(
        model, data, declared, best, null, members, before, after, cfg,
        final_ident.onset_ci,
    )  # fmt: skip
    for entry, eff in zip(identified, per_unit, strict=True):
        entry.update(fleet_summary(eff, entry))
    return DiagnosisResult(
        data, model, declared, tuple(library), ident, rescreen, verdict, identified,
        confounded, disc, before, after, added, tuple(members), tuple(per_unit),
        tuple(flags), note, cfg.identify.alpha,
    )  # fmt: skip


def _per_unit(model, data, declared, best, null, members, before, after, cfg, ci):
    """Per-unit verdicts of the added effects and the plausibility flags."""
    traj_after = unit_trajectories(model, data, best)
    traj_before = unit_trajectories(model, data, null)
    alpha = cfg.identify.alpha
    per_unit = unit_effects(model, data, best, members, alpha, traj_after, ci)
    values = {}
    for c in members:
        v = best.term_values(c)
        values[c.name] = v[list(c.carriers), 0] if c.per_unit else v
    flags = plausibility_flags(
        model, data, declared, per_unit, list(members), values, traj_after,
        traj_before, before.tracking_rmse, after.tracking_rmse, alpha,
    )  # fmt: skip
    return per_unit, flags
