"""The fallback when the library does not explain the residual: a discrepancy delta(w).

After the library is screened (:mod:`jaxcal.diagnosis.fitting.identify`), a
cross-validated ``delta(w)`` is fitted to the residual of the best model so far
(:mod:`jaxcal.diagnosis.fitting.discrepancy`, generalised
least squares under the noise model). If it is significant, the declared parameters
and delta are fitted by backfitting (Hastie & Tibshirani), the library is screened
again against that model, and three explanations are compared by one criterion:
delta alone, the first screen's winner beside delta, the rescreen's winner beside
delta — the BIC with delta's effective degrees of freedom counted, so a flexible
``delta(w)`` that absorbs a constant effect pays for it, and a library effect that
explains more is kept. ``cfg`` is the diagnosis's
:class:`~jaxcal.diagnosis.pipeline.LoopConfig`.
"""

from __future__ import annotations

import numpy as np

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.fitting.discrepancy import (
    Discrepancy,
    fit_discrepancy,
    predict_discrepancy,
)
from jaxcal.diagnosis.fitting.identify import identify
from jaxcal.diagnosis.fitting.joint import FitResult, fit_model, resume_at
from jaxcal.diagnosis.fitting.screen import spec_for


def whiten_normalised(data: LoopData):
    """Prewhitening of arrays in noise-std units (the discrepancy's residual), of
    every output or of ``outputs`` alone (:meth:`LoopData.whiten`)."""
    if data.noise.is_white:
        return None

    def whiten(arr, outputs=None):
        sigma = data.noise_std if outputs is None else data.noise_std[list(outputs)]
        shape = (1, -1) + (1,) * (arr.ndim - 2)
        return data.whiten(arr * sigma.reshape(shape), outputs)

    return whiten


def _delta(data, resid, cfg) -> Discrepancy:
    return fit_discrepancy(
        data.w, resid, data.unit, data.sensor_names, cfg.discrepancy,
        data.condition_names, whiten=whiten_normalised(data),
    )  # fmt: skip


def _backfit(model, data, spec, start: FitResult, cfg):
    """Alternate theta (and effects) with delta(w): Hastie & Tibshirani backfitting,
    from where ``start`` (a fit of the same terms) ended."""
    resume_at(model, data, start)  # its first evaluation is start's own
    fit = fit_model(model, data, spec, start.params, max_iters=cfg.max_iters)
    offset, disc = None, None
    for _ in range(cfg.discrepancy.backfit_rounds):
        raw = fit.evaluation.resid + (
            0.0 if offset is None else offset / data.noise_std
        )
        disc = _delta(data, raw, cfg)
        offset = predict_discrepancy(disc, data.w) * data.noise_std
        fit = fit_model(
            model, data, spec, fit.params, offset=offset, max_iters=cfg.max_iters
        )
    return fit, offset, disc


def _delta_df(disc: Discrepancy | None) -> float:
    """Effective degrees of freedom of the significant part of delta."""
    if disc is None:
        return 0.0
    return float(sum(s.df for s in disc.sensors if s.significant))


def _bic_with(fit: FitResult, disc: Discrepancy | None) -> float:
    """BIC of a fit beside delta, delta's effective degrees of freedom counted."""
    return fit.bic + _delta_df(disc) * np.log(max(fit.num_resid, 2))


def _fallback_note(bics, chosen, ident, rescreen) -> str:
    """What the fallback kept, and the BIC margins it decided by (``bics``: each
    option's BIC and its screen, delta alone first with ``None``)."""
    bic = {id(screen): value for value, screen in bics}
    delta_alone = bics[0][0]
    if chosen is None:
        dropped = [s.winner.name for s in (ident, rescreen) if s.winner is not None]
        if not dropped:
            return ""
        return (
            f"{' and '.join(dropped)} dropped: delta alone explains the data better "
            "(BIC with delta's degrees of freedom counted)"
        )
    other = rescreen if chosen is ident else ident
    which = "the screen's winner without delta" if chosen is ident else (
        "the winner of the screen against delta"
    )  # fmt: skip
    return (
        f"{chosen.winner.name} ({which}) kept beside delta: the BIC with delta's "
        f"degrees of freedom counted is {delta_alone - bic[id(chosen)]:.1f} lower "
        "than with delta alone"
        + (
            f" and {bic[id(other)] - bic[id(chosen)]:.1f}"
            " lower than with the other screen's winner"
            if ident.winner is not None and rescreen.winner is not None
            else ""
        )
    )


def fallback(model, data: LoopData, declared, library, ident, null: FitResult, cfg):
    """``(fit, offset, delta, identification, rescreen, note)``: the best of delta
    alone and either screen's winner beside it (module docstring), or ``ident``'s
    winner (or ``null``) with no delta when delta is not significant."""
    spec0 = null.spec
    best = ident.winner_fit if ident.winner is not None else null
    disc = _delta(data, best.evaluation.resid, cfg)
    if not disc.any_significant:
        return best, None, None, ident, None, ""
    fit_d, offset, disc = _backfit(model, data, spec0, null, cfg)
    # its fits are read by the noise passes alone, done by now: slimmed bare
    rescreen = identify(model, data, declared, library, cfg.identify, fit_d,
                        offset=offset, basis=False)._replace(fits={})  # fmt: skip
    # the options one by one, the best so far alone kept: a fit holds the fleet's
    # rows several times over (the peak of the diagnosis's memory was three of them)
    bics = [(_bic_with(fit_d, disc), None)]
    kept = (fit_d, offset, disc, None)
    del fit_d
    for screen in (ident, rescreen):
        if screen.winner is not None:
            spec = spec_for(declared, screen.winner.members, spec0.initial_state)
            fit_w, off_w, disc_w = _backfit(model, data, spec, screen.winner_fit, cfg)
            bic = _bic_with(fit_w, disc_w)
            if bic < min(b for b, _ in bics):  # ties: the first, as min() chose
                kept = (fit_w, off_w, disc_w, screen)
            bics.append((bic, screen))
            del fit_w, off_w, disc_w
    best, offset, disc, chosen = kept
    # delta alone won: the rescreen's winner lost beside it and is not added (its
    # members are not in the chosen fit, so nothing of it can be reported per unit)
    final = (
        chosen
        if chosen is not None
        else rescreen._replace(winner=None, winner_fit=None, confounded=[])
    )
    note = _fallback_note(bics, chosen, ident, rescreen)
    return best, offset, disc if disc.any_significant else None, final, rescreen, note
