"""Trace a residual to the library: screen, refit the finalists, rank, flag confounding.

1. **Screen.** At the declared-only fit, every candidate (and every pair of the best
   ``pair_top`` whose members do not reproduce each other's signature, see 4) is
   scored by the likelihood-ratio statistic of the *linearised* joint
   fit ``LR = SSR_0 - SSR_c`` (sigma known, so ``-2 log L = SSR``), computed for all
   candidates at once from the per-unit Gram blocks (:mod:`.fitting`): this is the
   score test of Rao (1948) in Gauss–Newton form.
2. **Refit.** The ``top_k`` singles and the pairs among the best ``pair_top`` are fitted
   jointly with the declared parameters by Levenberg–Marquardt, which replaces their
   linearised numbers.
3. **Rank** by BIC = SSR + k ln n (Schwarz 1978); the evidence for a candidate is
   ``delta_bic = BIC_0 - BIC_c`` and the LR test ``chi2(df = k_c)`` against the
   declared-only model. A winner is *found* when ``delta_bic >= bic_margin`` (10 is
   "very strong" on the scale of Kass & Raftery 1995) and its p-value is below
   ``alpha`` divided by the number of tests (Bonferroni). A pair must beat the best
   single by the margin too (parsimony).
4. **Confounding.** Candidates within ``bic_margin`` of the winner whose signature,
   after projecting out the declared parameters' signatures, reproduces at least
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

from jaxcal.diagnosis.effects import Candidate
from jaxcal.diagnosis.fitting import FitResult, fit_model
from jaxcal.diagnosis.prepare import LoopData
from jaxcal.diagnosis.screen import Screen, init_from, spec_for
from jaxcal.model import Model


@dataclasses.dataclass(frozen=True)
class IdentifyConfig:
    """Static settings of :func:`identify`."""

    top_k: int = 3  # singles refitted nonlinearly
    pair_top: int = 3  # pairs among this many best singles are scored and refitted
    alpha: float = 0.01  # family-wise level of the likelihood-ratio tests
    bic_margin: float = (
        10.0  # delta BIC needed for "found" (and for a pair over a single)
    )
    confound_r2: float = (
        0.9  # share of the winner's signal another candidate reproduces
    )
    absorbed_frac: float = 0.1  # projected / raw signature norm below this: absorbed
    max_iters: int = 20  # Levenberg–Marquardt iterations per refit

    def __post_init__(self):
        if self.top_k < 1 or self.pair_top < 0 or not 0 < self.alpha < 1:
            raise ValueError(
                "IdentifyConfig: need top_k >= 1, pair_top >= 0, 0 < alpha < 1"
            )


class RankEntry(NamedTuple):
    """One candidate model (a single effect or a pair) with its evidence."""

    name: str  # members joined by " + "
    members: tuple[str, ...]
    df: int  # parameters added to the declared-only model
    lr_stat: float  # SSR_0 - SSR_c (= 2 delta log-likelihood)
    log10_p: float  # log10 of the chi2(df) tail probability of lr_stat
    bic: float
    delta_bic: float  # BIC_0 - BIC_c, > 0 favours the candidate
    sizes: tuple[float, ...]  # per member, physical units (parameter: mean end value)
    stds: tuple[float, ...]  # per member
    refit: bool  # True: nonlinear joint refit; False: linearised screening
    detectability: float  # projected / raw signature norm (singles; 1 for pairs)


class Identification(NamedTuple):
    """Outcome of :func:`identify`."""

    null: FitResult
    ranking: list[RankEntry]  # best first
    winner: RankEntry | None  # significant best model, or None
    winner_fit: FitResult | None
    confounded: list[str]  # candidates confounded with the winner (winner first)
    absorbed: list[str]  # candidates the declared parameters can mimic
    num_tests: int
    fits: dict  # name -> FitResult of every refitted model


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


def _entry(members, df, lr, null, n_resid, sizes, stds, refit, detect) -> RankEntry:
    bic0 = null.bic
    bic = null.ssr - lr + (null.num_params + df) * np.log(max(n_resid, 2))
    log10_p = log10_chi2_sf(lr, df)
    return RankEntry(
        " + ".join(c.name for c in members),
        tuple(c.name for c in members),
        df,
        float(lr),
        log10_p,
        float(bic),
        float(bic0 - bic),
        tuple(sizes),
        tuple(stds),
        refit,
        float(detect),
    )


def effect_sizes(fit: FitResult, members, data: LoopData):
    """Physical sizes of the members of a fitted model and their standard errors.

    Constant effects: the fitted value and its standard error (inflated by the
    residual variance factor when that exceeds 1). Per-unit parameters: the mean over
    units of the departure from nominal at each unit's last row and its standard
    error across units.
    """
    s2 = max(1.0, fit.ssr / max(fit.num_resid - fit.num_params, 1))
    glob_vals, glob_std = fit.global_values(), np.sqrt(np.diag(fit.global_cov) * s2)
    sizes, stds = [], []
    last = data.starts[1:] - 1
    # the fit orders its constant effects as the library does, members may not
    order = [c.name for c in fit.spec.global_effects]
    for c in members:
        if c.per_unit:  # mean over units of the value at each unit's last row
            j = data.parameter_names.index(c.target)
            eol = fit.evaluation.theta[last, j] - data.parameter_nominal[j]
            sizes.append(float(eol.mean()))
            # one unit has no spread to estimate from: NaN (reported as n/a), not 0
            spread = eol.std() / np.sqrt(eol.size) if eol.size > 1 else np.nan
            stds.append(float(spread))
        else:
            gi = order.index(c.name)
            sizes.append(float(glob_vals[gi]))
            stds.append(float(glob_std[gi]))
    return sizes, stds


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
        data: the rows.
        declared: the calibrated parameters.
        library: candidate effects (:func:`.effects.build_library`).
        cfg: settings.
        null: the declared-only fit (the "before" calibration).
        offset: a fixed discrepancy term included in every refit (sensor units).

    Returns:
        :class:`Identification`.
    """
    screen = Screen(model, data, declared, library, null)
    n_resid = null.num_resid
    singles = []
    for cand in library:
        lr, sol = screen.score([cand])
        df = data.num_units * data.num_candidate_knots if cand.per_unit else 1
        if cand.per_unit:
            sizes, stds = [np.nan], [np.nan]
        else:
            var = np.linalg.pinv(sol.schur)[0, 0] if sol.schur.size else np.nan
            sizes, stds = [cand.scale * sol.global_step[0]], [cand.scale * np.sqrt(var)]
        singles.append(
            (
                cand,
                _entry(
                    [cand],
                    df,
                    lr,
                    null,
                    n_resid,
                    sizes,
                    stds,
                    False,
                    screen.detectability(cand),
                ),
            )
        )
    singles.sort(key=lambda t: t[1].bic)
    by_name = {c.name: c for c in library}
    entries = {e.name: e for _, e in singles}
    # two forms of one effect (an additive and a multiplicative drift of a sensor at
    # one operating point) are near collinear: as a pair they fit large cancelling
    # sizes, so a pair whose members reproduce each other is not formed
    pairs = [
        p
        for p in itertools.combinations([c for c, _ in singles[: cfg.pair_top]], 2)
        if max(screen.overlap(p[0], p[1]), screen.overlap(p[1], p[0])) < cfg.confound_r2
    ]
    for pair in pairs:
        lr, _ = screen.score(list(pair))
        df = sum(
            data.num_units * data.num_candidate_knots if c.per_unit else 1 for c in pair
        )
        e = _entry(pair, df, lr, null, n_resid, [np.nan] * 2, [np.nan] * 2, False, 1.0)
        entries[e.name] = e
    fits = {}

    def refit(members):
        spec = spec_for(declared, members)
        fit = fit_model(
            model,
            data,
            spec,
            init_from(null, spec, data),
            offset=offset,
            max_iters=cfg.max_iters,
        )
        name = " + ".join(c.name for c in members)
        fits[name] = fit
        sizes, stds = effect_sizes(fit, members, data)
        old = entries[name]
        entries[name] = _entry(
            members,
            old.df,
            null.ssr - fit.ssr,
            null,
            n_resid,
            sizes,
            stds,
            True,
            old.detectability,
        )

    for members in [[c] for c, _ in singles[: cfg.top_k]] + [list(p) for p in pairs]:
        refit(members)
    ranking = sorted(entries.values(), key=lambda e: e.bic)
    for _ in range(cfg.top_k):  # a linearised score may have ranked a model too low
        if ranking[0].refit:
            break
        refit([by_name[m] for m in ranking[0].members])
        ranking = sorted(entries.values(), key=lambda e: e.bic)
    num_tests = len(singles) + len(pairs)
    threshold = np.log10(cfg.alpha / num_tests)

    def significant(e):
        return e.delta_bic >= cfg.bic_margin and e.log10_p < threshold

    best_single = min(
        (e for e in entries.values() if len(e.members) == 1), key=lambda e: e.bic
    )
    winner = ranking[0]
    if len(winner.members) > 1 and winner.bic > best_single.bic - cfg.bic_margin:
        winner = best_single
    if not significant(winner) or winner.name not in fits:
        winner = None
    confounded, absorbed = [], []
    for cand, e in singles:
        if e.detectability < cfg.absorbed_frac:
            absorbed.append(cand.name)
    if winner is not None:
        for m in winner.members:
            group = [m]
            for cand, _ in singles:
                e = entries[cand.name]
                if cand.name in winner.members or e.bic > winner.bic + cfg.bic_margin:
                    continue
                if screen.overlap(by_name[m], cand) >= cfg.confound_r2:
                    group.append(cand.name)
            if len(group) > 1:
                confounded.extend(g for g in group if g not in confounded)
    return Identification(
        null,
        ranking,
        winner,
        None if winner is None else fits[winner.name],
        confounded,
        absorbed,
        num_tests,
        fits,
    )
