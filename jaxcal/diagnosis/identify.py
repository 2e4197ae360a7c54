"""Trace a residual to the library: screen every form, refit the finalists, rank.

1. **Screen** (:mod:`.screen`): at the declared-only fit, every candidate in each of
   its forms — fleet-wide (one value) and in the units that carry it (the carriers and,
   for a step, the onsets chosen by the screen) — and every pair of the best
   ``pair_top`` whose members do not reproduce each other's signature is scored by the
   linearised likelihood-ratio statistic of the prewhitened residual.
2. **Refit.** The ``top_k`` singles and the pairs are fitted jointly with the declared
   parameters by Levenberg–Marquardt, which replaces their linearised numbers.
3. **Rank** by the extended BIC, ``SSR + k ln n + 2 ln C(U, |C|)`` per units term
   (Schwarz 1978; Chen & Chen 2008): one criterion for every kind and form, so a step
   is told from a drift, a bias and a gain by how well each explains the data, never
   by the order they are tried in, and a fleet-wide form from a per-unit one by the
   same rule. The evidence for a candidate is ``delta_bic = BIC_0 - BIC_c`` and the LR
   test ``chi2(df = k_c)`` against the declared-only model. A winner is *found* when
   ``delta_bic >= bic_margin`` (10 is "very strong" on the scale of Kass & Raftery
   1995) and its p-value is below ``alpha`` over the number of tests (Bonferroni). A
   pair must beat the best single by the margin too (parsimony).
4. **Confounding.** Candidates (another kind or target) within ``bic_margin`` of the
   winner, or explaining as much of the residual (their likelihood-ratio statistic
   within the margin: a rival cause whose signature spans the winner's, e.g. a
   change of a pressure-loss coefficient and a gain drift of the one pressure sensor
   it scales, loses on the BIC only by its freedom), whose signature, after
   projecting out the declared parameters' signatures, reproduces at least
   ``confound_r2`` of the winner's fitted signal are reported as confounded with it.
   Candidates whose projected signature keeps less than ``absorbed_frac`` of its norm
   are flagged *absorbed*: the declared parameters can mimic them, so they smear into
   theta instead of showing in the residual.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats as sps
from scipy.special import gammaln

from jaxcal.diagnosis.fitting import FitResult, fit_model
from jaxcal.diagnosis.kinds import Candidate, nests
from jaxcal.diagnosis.onsets import polish_onsets, refine_onsets
from jaxcal.diagnosis.prepare import LoopData
from jaxcal.diagnosis.screen import (
    ONSET_GRID,
    ONSET_GRID_DYNAMIC,
    Screen,
    init_from,
    spec_for,
)
from jaxcal.model import Model

ONSET_ROUNDS = 2  # profile a step's onsets at the fit, refit when one moved


@dataclasses.dataclass(frozen=True)
class IdentifyConfig:
    """Static settings of :func:`identify`."""

    top_k: int = 4  # singles refitted nonlinearly
    pair_top: int = 3  # pairs among this many best singles are scored and refitted
    alpha: float = 0.01  # family-wise level of the likelihood-ratio tests
    bic_margin: float = 10.0  # delta BIC needed for "found" (and a pair over a single)
    confound_r2: float = 0.9  # share of the winner's signal another reproduces
    absorbed_frac: float = 0.1  # projected / raw signature norm below this: absorbed
    max_iters: int = 20  # Levenberg–Marquardt iterations per refit
    # forms tried: without "units" every effect is fleet-wide or on every unit (the
    # diagnosis before issue 24; steps need the per-unit form and are left out)
    forms: tuple[str, ...] = ("fleet", "units")

    def __post_init__(self):
        if self.top_k < 1 or self.pair_top < 0 or not 0 < self.alpha < 1:
            raise ValueError(
                "IdentifyConfig: need top_k >= 1, pair_top >= 0, 0 < alpha < 1"
            )
        if not self.forms or not set(self.forms) <= {"fleet", "units"}:
            raise ValueError("IdentifyConfig.forms: a subset of ('fleet', 'units')")


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


class Identification(NamedTuple):
    """Outcome of :func:`identify`."""

    null: FitResult
    ranking: list[RankEntry]  # best first
    winner: RankEntry | None  # significant best model, or None
    winner_fit: FitResult | None
    confounded: list[str]  # effects confounded with the winner (winner first)
    absorbed: list[str]  # effects the declared parameters can mimic
    num_tests: int
    fits: dict  # entry name -> FitResult of every refitted model
    onset_ci: dict  # candidate key -> [U, 2] rows of a step's onset interval
    # the candidate no unit showed on its own with the largest summed unit score, on
    # every unit, and that sum: a basis for the noise model (pipeline), never a verdict
    near_miss: tuple = ()  # (Candidate, LR) or ()


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


def _price(members: Sequence[Candidate], data: LoopData) -> tuple[int, float]:
    """``(df, selection)`` of adding ``members``: coefficients (and onsets) and the
    extended BIC's price of the units terms' carriers."""
    df, sel, u = 0, 0.0, data.num_units
    for c in members:
        per = c.kind.num_free(data.num_candidate_knots)
        if c.per_unit:
            m = len(c.carriers)
            df += per * m
            sel += 2.0 * float(gammaln(u + 1) - gammaln(m + 1) - gammaln(u - m + 1))
        else:
            df += per
    return df, sel


def _entry(members, lr, null, data, sizes, stds, refit, detect) -> RankEntry:
    df, sel = _price(members, data)
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


def _singles(screen: Screen, library, null, data, forms=("fleet", "units")):
    """Every library candidate in each of its forms, screened; and the near miss
    (:class:`Identification`)."""
    out, onset_ci, near = [], {}, ()
    for cand in library:
        if "units" not in forms and not cand.kind.fleet:
            if cand.kind.profile == "step":
                continue
            every = cand.with_form("units", range(data.num_units))
            lr = float(screen.unit_scores(cand).lr.sum())
            det = screen.detectability(every)
            out.append(_entry([every], lr, null, data, [np.nan], [np.nan], False, det))
            continue
        detect = screen.detectability(
            cand.with_form("units", range(data.num_units))
            if cand.kind.profile == "step" or not cand.kind.fleet
            else cand
        )
        if cand.kind.fleet:
            lr, coef, var = screen.fleet_score(cand)
            fleet = cand.with_form("fleet")
            out.append(_entry([fleet], lr, null, data, [cand.scale * coef],
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
            out.append(_entry([units], lr, null, data, [size], [np.nan], False, detect))
    return out, onset_ci, near


def _profile_onsets(model, data, declared, members, fit, offset, cfg):
    """``(members, fit, intervals)`` with every per-unit step's onsets profiled at
    the fitted point (:mod:`.onsets`) and the model refitted when one moved."""
    steps = [i for i, c in enumerate(members)
             if c.kind.profile == "step" and c.per_unit]  # fmt: skip
    intervals = {}
    if not steps:
        return members, fit, intervals
    grid = ONSET_GRID_DYNAMIC if model.is_stateful else ONSET_GRID
    window = int(np.ceil(np.diff(data.starts).max() / grid)) + 2
    for _ in range(ONSET_ROUNDS):
        moved, members = False, list(members)
        for i in steps:
            new, ci = refine_onsets(model, data, fit, members[i], window)
            members_i = list(members)
            members_i[i] = new
            new = polish_onsets(model, data, fit, members_i, i, window)
            for u, row in zip(new.carriers, new.onsets, strict=True):
                ci[u] = [min(ci[u][0], row), max(ci[u][1], row)]
            intervals[new.name] = ci
            moved |= new.onsets != members[i].onsets
            members[i] = new
        if not moved:
            break
        spec = spec_for(declared, members, fit.spec.initial_state)
        fit = fit_model(model, data, spec, fit.params, offset=offset,
                        max_iters=cfg.max_iters)  # fmt: skip
    return members, fit, intervals


def identify(
    model: Model,
    data: LoopData,
    declared: Sequence[str],
    library: Sequence[Candidate],
    cfg: IdentifyConfig,
    null: FitResult,
    *,
    offset: np.ndarray | None = None,
) -> Identification:
    """Rank the library against the residual of the declared-only fit ``null``.

    Args:
        model: the model.
        data: the rows (with their noise model).
        declared: the calibrated parameters.
        library: candidate effects (:func:`.kinds.build_library`).
        cfg: settings.
        null: the declared-only fit (the "before" calibration).
        offset: a fixed discrepancy term included in every refit (output units).

    Returns:
        :class:`Identification`.
    """
    screen = Screen(model, data, library, null)
    singles, onset_ci, near_miss = _singles(screen, library, null, data, cfg.forms)
    singles.sort(key=lambda e: e.bic)
    entries = {e.name: e for e in singles}
    top = []
    for e in singles:  # the best form of each of the best effects
        if all(e.members[0].name != t.members[0].name for t in top):
            top.append(e)
        if len(top) >= cfg.pair_top:
            break
    pairs = [
        (a.members[0], b.members[0])
        for a, b in itertools.combinations(top, 2)
        if max(screen.overlap(a.members[0], b.members[0]),
               screen.overlap(b.members[0], a.members[0])) < cfg.confound_r2
    ]  # fmt: skip
    for pair in pairs:
        lr = screen.joint(pair)[0]
        e = _entry(pair, lr, null, data, [np.nan] * 2, [np.nan] * 2, False, 1.0)
        entries[e.name] = e
    fits = {}
    initial_state = null.spec.initial_state

    refined_ci = {}  # entry name -> {step name: [U, 2] profiled onset interval}

    def refit(members):
        spec = spec_for(declared, members, initial_state)
        fit = fit_model(
            model, data, spec, init_from(null, model, data, spec), offset=offset,
            max_iters=cfg.max_iters,
        )  # fmt: skip
        name = " + ".join(c.label for c in members)
        members, fit, refined_ci[name] = _profile_onsets(
            model, data, declared, members, fit, offset, cfg
        )
        fits[name] = fit
        sizes, stds = effect_sizes(fit, members, data)
        old = entries[name]
        entries[name] = _entry(members, null.ssr - fit.ssr, null, data, sizes, stds,
                               True, old.detectability)  # fmt: skip

    for e in singles[: cfg.top_k]:
        refit(list(e.members))
    for pair in pairs:
        refit(list(pair))
    ranking = sorted(entries.values(), key=lambda e: e.bic)
    for _ in range(cfg.top_k):  # a linearised score may have ranked a model too low
        if not ranking or ranking[0].refit:
            break
        refit(list(ranking[0].members))
        ranking = sorted(entries.values(), key=lambda e: e.bic)
    num_tests = len(singles) + len(pairs)
    threshold = np.log10(cfg.alpha / max(num_tests, 1))

    def significant(e):
        return e.delta_bic >= cfg.bic_margin and e.log10_p < threshold

    winner = ranking[0] if ranking else None  # empty: no unit shows any candidate
    best_single = min(
        (e for e in entries.values() if len(e.members) == 1 and e.refit),
        key=lambda e: e.bic,
        default=None,
    )
    if winner is not None and len(winner.members) > 1 and best_single is not None:
        if winner.bic > best_single.bic - cfg.bic_margin:
            winner = best_single
    if winner is None or not significant(winner) or winner.name not in fits:
        winner = None
    absorbed = sorted({e.members[0].name for e in singles
                       if e.detectability < cfg.absorbed_frac})  # fmt: skip
    confounded = []
    if winner is not None:
        for m in winner.members:
            group = [m.name]
            for e in singles:
                other = e.members[0]
                if other.name in winner.member_names or other.name in group:
                    continue
                if nests(other, m) or nests(m, other):
                    continue
                e = entries.get(e.name, e)  # the refitted numbers where there are
                if (
                    e.bic > winner.bic + cfg.bic_margin
                    and e.lr_stat < winner.lr_stat - cfg.bic_margin
                ):
                    continue  # worse by the margin, penalised and unpenalised
                if screen.overlap(m, other) >= cfg.confound_r2:
                    group.append(other.name)
            if len(group) > 1:
                confounded.extend(g for g in group if g not in confounded)
    if winner is not None:  # the winner's onsets were profiled at its own fit
        onset_ci.update(refined_ci.get(winner.name, {}))
    return Identification(
        null, ranking, winner, None if winner is None else fits[winner.name],
        confounded, absorbed, num_tests, fits, onset_ci, near_miss,
    )  # fmt: skip
