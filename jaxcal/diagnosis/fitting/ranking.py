"""The evidence for one candidate model and the screening of the library.

A :class:`RankEntry` holds a candidate model's likelihood-ratio statistic against the
declared-only fit, its chi2 p-value (finite far into the tail, :func:`log10_chi2_sf`)
and its extended BIC, whose price counts the coefficients and the choice of carriers
of a per-unit term (module docstring of :mod:`jaxcal.diagnosis.fitting.identify`, step
3). :func:`screened_singles` scores every candidate of the library in each of its
forms at the declared-only fit (step 1); :func:`effect_sizes` reads the physical sizes
of a refitted model's members.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats as sps
from scipy.special import gammaln

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.fitting.joint import FitResult
from jaxcal.diagnosis.fitting.screen import Screen
from jaxcal.diagnosis.kinds.table import Candidate
from jaxcal.diagnosis.kinds.terms import ModelSpec, selection_penalty


class RankEntry(NamedTuple):
    """One candidate model (a single effect in one form, or a pair) and its evidence."""

    name: str  # members' labels joined by " + "
    members: tuple[Candidate, ...]
    df: int  # parameters added to the declared-only model
    lr_stat: float  # SSR_0 - SSR_c (= 2 delta log-likelihood)
    log10_p: float  # log10 of the chi2(df) tail probability of lr_stat
    bic: float  # extended BIC (carriers' price included)
    delta_bic: float  # BIC_0 - BIC_c, > 0 favours the candidate
    sizes: tuple[float, ...]  # per member, physical units (mean over its carriers)
    stds: tuple[float, ...]  # per member
    refit: bool  # True: nonlinear joint refit; False: linearised screening
    detectability: float  # projected / raw signature norm (singles; 1 for pairs)

    @property
    def member_names(self) -> tuple[str, ...]:
        """The members' effect names (without their form)."""
        return tuple(c.name for c in self.members)


def log10_chi2_sf(x: float, df: int) -> float:
    """log10 of the chi2(df) tail probability, finite far into the tail.

    Where scipy's ``logsf`` underflows, the leading term of the asymptotic series of
    the upper incomplete gamma function is used (Abramowitz & Stegun 6.5.32).
    """
    if df <= 0:
        return 0.0
    value = float(sps.chi2.logsf(x, df))
    if not np.isfinite(value):
        half = 0.5 * x
        value = -half + (0.5 * df - 1.0) * np.log(half) - float(gammaln(0.5 * df))
    return value / np.log(10.0)


def rank_entry(members, lr, null, data, sizes, stds, refit, detect) -> RankEntry:
    """The entry of ``members`` whose likelihood-ratio statistic against the
    declared-only fit ``null`` is ``lr``: its price (coefficients and onsets, and the
    extended BIC's price of the units terms' carriers), p-value and BIC."""
    df = sum(c.kind.num_free(data.num_candidate_knots)
             * (len(c.carriers) if c.per_unit else 1) for c in members)  # fmt: skip
    sel = selection_penalty(data, ModelSpec((), tuple(members)))
    log_n = np.log(max(null.num_resid, 2))
    bic = null.bic - lr + df * log_n + sel
    return RankEntry(
        " + ".join(c.label for c in members), tuple(members), df, float(lr),
        log10_chi2_sf(lr, df), float(bic), float(null.bic - bic), tuple(sizes),
        tuple(stds), refit, float(detect),
    )  # fmt: skip


def effect_sizes(fit: FitResult, members: Sequence[Candidate], data: LoopData):
    """Physical sizes of the members of a fitted model and their standard errors.

    A fleet term: its value and standard error (inflated by the residual variance
    factor when that exceeds 1). A units term: the mean over its carriers (a spline:
    of the departure from nominal at each carrier's last row) and the standard error
    of that mean across them (NaN with one carrier).
    """
    s2 = max(1.0, fit.ssr / max(fit.num_resid - fit.num_params, 1))
    glob = fit.spec.global_terms
    sizes, stds = [], []
    last = data.starts[1:] - 1
    for c in members:
        if not c.per_unit:
            g = [t.key for t in glob].index(c.key)
            sizes.append(float(fit.term_values(c)[0]))
            stds.append(float(np.sqrt(fit.global_cov[g, g] * s2)))
            continue
        carriers = np.asarray(c.carriers, int)
        if c.kind.channel == "parameter" and c.kind.profile == "spline":
            j = data.parameter_names.index(c.target)
            vals = fit.evaluation.theta[last[carriers], j] - data.parameter_nominal[j]
        else:
            vals = fit.term_values(c)[carriers, 0]
        sizes.append(float(np.mean(vals)))
        spread = np.std(vals) / np.sqrt(vals.size) if vals.size > 1 else np.nan
        stds.append(float(spread))
    return sizes, stds


def screened_singles(screen: Screen, library, null, data, forms=("fleet", "units")):
    """Every library candidate in each of its forms, screened: ``(entries, onset
    intervals of the steps, the near miss)``
    (:class:`jaxcal.diagnosis.fitting.identify.Identification`)."""
    out, onset_ci, near = [], {}, ()
    for cand in library:
        if "units" not in forms and not cand.kind.fleet:
            if cand.kind.profile == "step":
                continue
            every = cand.with_form("units", range(data.num_units))
            lr = float(screen.unit_scores(cand).lr.sum())
            det = screen.detectability(every)
            out.append(
                rank_entry([every], lr, null, data, [np.nan], [np.nan], False, det)
            )
            continue
        detect = screen.detectability(
            cand.with_form("units", range(data.num_units))
            if cand.kind.profile == "step" or not cand.kind.fleet
            else cand
        )
        if cand.kind.fleet:
            lr, coef, var = screen.fleet_score(cand)
            fleet = cand.with_form("fleet")
            out.append(rank_entry([fleet], lr, null, data, [cand.scale * coef],
                              [cand.scale * np.sqrt(var)], False, detect))  # fmt: skip
        if "units" not in forms:
            continue
        units, scores = screen.units_form(cand)
        if cand.kind.profile == "step":
            onset_ci[cand.name] = scores.onset_ci
        total = float(np.sum(scores.lr))
        if units is None and total > (near[1] if near else 0.0):
            every = range(data.num_units)
            onsets = scores.onset if cand.kind.profile == "step" else ()
            near = (cand.with_form("units", every, onsets), total)
        if units is not None:
            carriers = list(units.carriers)
            lr = float(scores.lr[carriers].sum())
            size = cand.scale * float(np.nanmean(scores.estimate[carriers]))
            out.append(
                rank_entry([units], lr, null, data, [size], [np.nan], False, detect)
            )
    return out, onset_ci, near
