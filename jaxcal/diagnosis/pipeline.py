"""Close the loop on one data set: calibrate, trace the residual, add the effect.

:func:`diagnose` runs the steps of design/loop.md on any static
:class:`~jaxcal.model.Model` and a :class:`~jaxcal.data.dataset.Dataset` (time =
cycle; a turbofan :class:`~jaxcal.data.record.Record` is converted):

1. **Calibrate** the declared parameters (per-unit splines in time, jointly over
   the data) — the "before" model. When the noise levels are not given they are
   estimated from this fit's residual (:func:`.noise.estimate_noise_std`), outputs
   whose readings are quantised are dropped, and the fit is repeated.
2. **Trace** the normalised residual to the library (:func:`.identify.identify`).
3. **Fallback.** A cross-validated ``delta(w)`` is fitted to the residual of the best
   model so far (:mod:`.discrepancy`). If it is significant, the declared parameters
   and delta are fitted by backfitting (alternating), the library is screened again
   against that model, and an effect is kept only if it is still significant beyond
   delta — a smooth ``delta(w)`` can mimic any constant effect, so the library is
   preferred when it explains the data and delta takes only what it cannot.
4. **Add** the chosen effect(s) (declared from now on), refit, and report the errors
   before and after: tracking RMSE per sensor, theta RMSE where the truth is known and
   residual whiteness.
5. **Per unit and plausibility.** Each added effect gets its size, carriers (a
   Holm-corrected z-test across units) and onset per unit (:mod:`.units`), and the
   final fit is checked against the model's bounds and direction of wear
   (:mod:`.plausibility`); triggered checks are flags on the verdict.

The fallback never discards a library effect that explains the residual better: when
the screen against delta finds nothing but the screen without it did, the first winner
is kept (refitted with delta) unless delta alone has the lower BIC, delta's effective
degrees of freedom counted.

Verdicts (:data:`VERDICTS`): ``none`` (nothing found), ``identified``, ``confounded``
(the winner shares its signature with others within the BIC margin; the set is reported,
the winner only stands in for it in the "after" model), ``discrepancy`` (delta only)
and ``identified+discrepancy`` / ``confounded+discrepancy``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.diagnosis.discrepancy import (
    Discrepancy,
    DiscrepancyConfig,
    fit_discrepancy,
    predict_discrepancy,
)
from jaxcal.diagnosis.effects import Candidate, build_library
from jaxcal.diagnosis.fitting import FitResult, ModelSpec, fit_model
from jaxcal.diagnosis.identify import (
    Identification,
    IdentifyConfig,
    effect_sizes,
    identify,
)
from jaxcal.diagnosis.noise import estimate_noise_std
from jaxcal.diagnosis.plausibility import plausibility_flags
from jaxcal.diagnosis.prepare import LoopData, prepare_data
from jaxcal.diagnosis.residuals import ResidualSummary, summarize_residuals
from jaxcal.diagnosis.screen import spec_for
from jaxcal.diagnosis.units import unit_effects, unit_trajectories
from jaxcal.model import Model

VERDICTS = (
    "none",
    "identified",
    "confounded",
    "discrepancy",
    "identified+discrepancy",
    "confounded+discrepancy",
)


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Static settings of the diagnosis."""

    knots: int = 6  # B-spline functions per unit for each declared parameter
    candidate_knots: int = 3  # ... for each candidate (undeclared) parameter
    families: tuple[str, ...] = ()  # restrict the library (empty: all families)
    identify: IdentifyConfig = IdentifyConfig()
    discrepancy: DiscrepancyConfig = DiscrepancyConfig()
    max_lag: int = 10  # autocorrelation lags / Ljung–Box h
    max_iters: int = 20  # Levenberg–Marquardt iterations of the declared-only fit


class Stage(NamedTuple):
    """A calibrated model and its errors ("before" or "after")."""

    fit: FitResult
    offset: np.ndarray | None  # [N, S] discrepancy term, sensor units
    summary: ResidualSummary
    tracking_rmse: np.ndarray  # [S] sensor units
    tracking_rmse_norm: np.ndarray  # [S] multiples of the noise std
    theta_rmse: dict  # parameter -> RMSE against the truth (empty without truth)
    whiteness: float  # share of sensors whose Ljung–Box test passes at 1 %


class DiagnosisResult(NamedTuple):
    """Everything :mod:`.report` writes."""

    data: LoopData
    declared: tuple[str, ...]
    library: tuple[Candidate, ...]
    identification: Identification  # the library against the declared-only residual
    rescreen: Identification | None  # again, against declared + delta (when delta fits)
    verdict: str
    identified: list  # dicts: name, kind, size, std, unit (the added effects)
    confounded: list  # names, when the verdict is "confounded"
    discrepancy: Discrepancy | None  # significant delta(w), or None
    before: Stage
    after: Stage
    added: list  # names of the model terms added for "after"
    unit_effects: tuple = ()  # units.UnitEffect per added library effect
    flags: tuple = ()  # plausibility flags (dicts, plausibility.FLAGS)
    fallback_note: str = ""  # what the fallback kept or dropped, and why
    alpha: float = 0.01  # level of the per-unit test and bands


def make_stage(
    data: LoopData, fit: FitResult, offset, max_lag: int, theta_names=()
) -> Stage:
    """Errors of a fitted model on the rows where the model is valid.

    ``theta_rmse`` covers the fitted parameters and ``theta_names`` that have a true
    value in the data (a parameter the model does not fit is held at its nominal
    value, so its RMSE is the size of its departure).
    """
    valid = fit.evaluation.valid
    r = fit.evaluation.resid
    err = r[valid] * data.noise_std
    theta_rmse = {}
    if data.theta_true is not None:
        names = list(fit.spec.unit_params)
        names += [n for n in theta_names if n not in names]
        for name in names:
            if name not in data.theta_names:
                continue
            j = data.parameter_names.index(name)
            t = data.theta_names.index(name)
            diff = fit.evaluation.theta[valid, j] - data.theta_true[valid, t]
            theta_rmse[name] = float(np.sqrt(np.mean(diff**2)))
    summary = summarize_residuals(
        r, data.w, data.cycle, data.starts, max_lag=min(max_lag, data.num_rows - 1)
    )
    return Stage(
        fit,
        offset,
        summary,
        np.sqrt(np.mean(err**2, axis=0)),
        np.sqrt(np.mean(r[valid] ** 2, axis=0)),
        theta_rmse,
        float(np.mean(summary.ljung_box_p > 0.01)),
    )


def _backfit(model, data, spec, init, cfg: LoopConfig):
    """Alternate theta (and effects) with delta(w): Hastie & Tibshirani backfitting."""
    fit, offset, disc = (
        fit_model(model, data, spec, init, max_iters=cfg.max_iters),
        None,
        None,
    )
    for _ in range(cfg.discrepancy.backfit_rounds):
        raw = fit.evaluation.resid + (
            0.0 if offset is None else offset / data.noise_std
        )
        disc = fit_discrepancy(
            data.w, raw, data.unit, data.sensor_names, cfg.discrepancy,
            data.condition_names,
        )  # fmt: skip
        offset = predict_discrepancy(disc, data.w) * data.noise_std
        fit = fit_model(
            model, data, spec, fit.params, offset=offset, max_iters=cfg.max_iters
        )
    return fit, offset, disc


def _effects_of(ident: Identification, fit: FitResult, library, data) -> list:
    by_name = {c.name: c for c in library}
    members = [by_name[m] for m in ident.winner.members]
    sizes, stds = effect_sizes(fit, members, data)
    return [
        {
            "name": c.name,
            "kind": c.kind,
            "family": c.family,
            "target": c.target,
            "size": s,
            "std": e,
            "unit": c.unit,
        }
        for c, s, e in zip(members, sizes, stds, strict=True)
    ]


def _as_dataset(data) -> tuple[Dataset, int | None]:
    """A Dataset and the reader's dropped-row count (a Record is converted)."""
    if isinstance(data, Dataset):
        return data, None
    if hasattr(data, "x_names") and hasattr(data, "cycle"):  # a turbofan Record
        from jaxcal.data.readers import dataset_from_record

        return dataset_from_record(data), int(data.dropped_rows)
    raise ValueError(
        f"data must be a jaxcal Dataset (or a turbofan Record), got {type(data)}"
    )


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
) -> DiagnosisResult:
    """Find the residual, trace it to an effect, add it and compare (module docstring).

    Args:
        data: a :class:`~jaxcal.data.dataset.Dataset` (``time`` = cycle) or a
            turbofan ``Record``.
        model: a :class:`~jaxcal.model.Model` (one with hidden states is
            diagnosed on its one-step prediction, :mod:`.one_step`) or a
            ``jaxcal.models.load`` spec; float64 must be enabled by the caller.
        declared: the calibrated (declared) parameters.
        cfg: settings.
        sensors: outputs of the residual (default: all usable).
        units: units to use (default: all).
        max_rows: subsample to about this many rows.
        noise_std: known noise std by output (default: estimated).

    Returns:
        :class:`DiagnosisResult`.
    """
    if not isinstance(model, Model):
        from jaxcal.models import load

        model = load(model)
    declared = tuple(declared)
    if not declared or len(set(declared)) != len(declared):
        raise ValueError(f"calibrate must name distinct parameters, got {declared}")
    model.parameter_index(declared)
    dataset, dropped_rows = _as_dataset(data)
    state_note = None
    if model.is_stateful:  # one-step residuals (jaxcal.diagnosis.one_step)
        from jaxcal.diagnosis.one_step import one_step_data, one_step_model

        dataset, state_note = one_step_data(
            model, dataset, declared, noise_std, sensors
        )
        model = one_step_model(model)
    data = prepare_data(
        dataset,
        model,
        sensors=sensors,
        units=units,
        max_rows=max_rows,
        knots=cfg.knots,
        candidate_knots=cfg.candidate_knots,
        noise_std=noise_std,
        dropped_rows=dropped_rows,
    )
    if state_note is not None:
        data = dataclasses.replace(data, notes=(state_note, *data.notes))
    spec0 = ModelSpec(declared)
    null = fit_model(model, data, spec0, max_iters=cfg.max_iters)
    if not null.evaluation.valid.all():
        bad = int(np.sum(~null.evaluation.valid))
        data = data.take_rows(
            null.evaluation.valid,
            f"{bad} rows dropped: the model is invalid there (did not converge or "
            "inputs outside its range)",
        )
        null = fit_model(model, data, spec0, max_iters=cfg.max_iters)
    if noise_std is None:
        resid = null.evaluation.resid * data.noise_std
        std, reasons = estimate_noise_std(data, resid)
        std = np.where(std > 0, std, data.noise_std)
        data = data.with_noise(std, "estimated").drop_sensors(reasons)
        null = fit_model(model, data, spec0, null.params, max_iters=cfg.max_iters)
    w_std = data.w.std(0)
    condition_scale = 0.01 * np.where(
        w_std > 0, w_std, np.maximum(np.abs(data.w).mean(0), 1.0)
    )
    library = build_library(
        model,
        declared,
        data.sensor_names,
        data.noise_std,
        np.abs(data.x).mean(0),
        condition_scale,
        families=cfg.families or None,
    )
    if not library:
        raise ValueError(
            f"the effect library is empty for families {cfg.families} with "
            f"calibrate={list(declared)}"
        )
    ident = identify(model, data, declared, library, cfg.identify, null)
    best = ident.winner_fit if ident.winner is not None else null
    disc = fit_discrepancy(
        data.w, best.evaluation.resid, data.unit, data.sensor_names, cfg.discrepancy,
        data.condition_names,
    )  # fmt: skip
    offset, final_ident, rescreen, note = None, ident, None, ""
    if disc.any_significant:
        fit_d, offset, disc = _backfit(model, data, spec0, null.params, cfg)
        final_ident = rescreen = identify(
            model, data, declared, library, cfg.identify, fit_d, offset=offset
        )
        best = fit_d
        if final_ident.winner is None and ident.winner is not None:
            kept = _keep_winner(model, data, declared, library, ident, fit_d, disc, cfg)
            if kept is not None:
                final_ident, note = ident, kept[3]
                best, offset, disc = kept[:3]
            else:
                note = (
                    f"{ident.winner.name} (the screen's winner without delta) was "
                    "dropped: delta alone explains the data better (BIC with "
                    "delta's degrees of freedom counted)"
                )
        elif final_ident.winner is not None:
            spec = spec_for(
                declared, [c for c in library if c.name in final_ident.winner.members]
            )
            best, offset, disc = _backfit(
                model, data, spec, final_ident.winner_fit.params, cfg
            )
        if not disc.any_significant:
            disc = None
    else:
        disc = None
    identified, confounded, added = [], [], []
    if final_ident.winner is not None:
        identified = _effects_of(final_ident, best, library, data)
        added = list(final_ident.winner.members)
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
    by_name = {c.name: c for c in library}
    members = [by_name[e["name"]] for e in identified]
    per_unit, flags = _per_unit(
        model, data, declared, best, null, members, before, after, cfg
    )
    for entry, eff in zip(identified, per_unit, strict=True):
        entry.update(_fleet_summary(eff, entry))
    return DiagnosisResult(
        data,
        declared,
        library,
        ident,
        rescreen,
        verdict,
        identified,
        confounded,
        disc,
        before,
        after,
        added,
        tuple(per_unit),
        tuple(flags),
        note,
        cfg.identify.alpha,
    )


def _delta_df(disc: Discrepancy | None) -> float:
    """Effective degrees of freedom of the significant part of delta."""
    if disc is None:
        return 0.0
    return float(sum(s.df for s in disc.sensors if s.significant))


def _keep_winner(model, data, declared, library, ident, fit_d, disc_d, cfg):
    """``(fit, offset, delta, note)`` with the first screen's winner beside delta when
    that explains the data at least as well as delta alone, else ``None``.

    "As well" is the BIC with delta's effective degrees of freedom counted: a flexible
    delta(w) that absorbs a constant effect pays for it, so it displaces a library
    effect only when it fits better at its price (the library is preferred, module
    docstring).
    """
    members = [c for c in library if c.name in ident.winner.members]
    fit_w, offset_w, disc_w = _backfit(
        model, data, spec_for(declared, members), ident.winner_fit.params, cfg
    )
    log_n = np.log(max(fit_w.num_resid, 2))
    bic_d = fit_d.bic + _delta_df(disc_d) * log_n
    bic_w = fit_w.bic + _delta_df(disc_w) * log_n
    if bic_w > bic_d:
        return None
    note = (
        f"{ident.winner.name} kept beside delta: the BIC with delta's degrees of "
        f"freedom counted is {bic_d - bic_w:.1f} lower than with delta alone"
    )
    return fit_w, offset_w, disc_w, note


def _per_unit(model, data, declared, best, null, members, before, after, cfg):
    """Per-unit verdicts of the added effects and the plausibility flags."""
    traj_after = unit_trajectories(model, data, best)
    traj_before = unit_trajectories(model, data, null)
    alpha = cfg.identify.alpha
    per_unit = unit_effects(model, data, best, members, alpha, traj_after)
    values = dict(
        zip(
            [c.name for c in best.spec.global_effects],
            best.global_values().tolist(),
            strict=True,
        )
    )
    effect_values = {
        c.name: (c.target, c.family, values[c.name]) for c in best.spec.global_effects
    }
    flags = plausibility_flags(
        model, data, declared, per_unit, effect_values, traj_after, traj_before,
        before.tracking_rmse, after.tracking_rmse, alpha,
    )  # fmt: skip
    return per_unit, flags


def _fleet_summary(eff, entry: dict) -> dict:
    """Fleet numbers of one effect from the same final fit as its per-unit values.

    A per-unit parameter's fleet size is the mean over units of its change over each
    record (the per-unit size), beside the mean values at the first and the last
    cycle; its standard error is that of the mean, at least the units' own mean
    standard error (so a single unit does not get 0). Carriers and the rest are
    summarised apart, since a fleet mean blends them.
    """
    out = {"carriers": int(eff.carries.sum())}
    if entry["family"] == "parameter":
        u = eff.size.size
        spread = float(np.var(eff.size, ddof=1)) / u if u > 1 else 0.0
        own = float(np.mean(eff.size_std**2)) / u
        out["size"] = float(np.mean(eff.size))
        out["std"] = float(np.sqrt(max(spread, own)))
        out["start_value"] = float(np.mean(eff.start_value))
        out["end_value"] = float(np.mean(eff.start_value + eff.size))
    for key, mask in (("size_carriers", eff.carries), ("size_others", ~eff.carries)):
        out[key] = float(np.mean(eff.size[mask])) if mask.any() else None
    return out


# The name of the turbofan-era entry point, kept for callers of the old API.
diagnose_record = diagnose
