"""Trace a residual to the library: screen every form, refit the finalists, rank.

1. **Screen** (:mod:`jaxcal.diagnosis.fitting.screen`): at the declared-only fit, every
   candidate in each of its forms — fleet-wide (one value) and in the units that carry
   it (the carriers and, for a step, the onsets chosen by the screen) — and every pair
   of the best ``pair_top`` whose members do not reproduce each other's signature is
   scored by the linearised likelihood-ratio statistic of the prewhitened residual.
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

An entry's evidence (price, p-value, BIC) and the screening of step 1 are in
:mod:`jaxcal.diagnosis.fitting.ranking`.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.fitting.joint import (
    FitResult,
    fit_model,
    local_remake,
    raw_columns_of,
    resume_at,
)
from jaxcal.diagnosis.fitting.ranking import (
    RankEntry,
    effect_sizes,
    rank_entry,
    screened_singles,
)
from jaxcal.diagnosis.fitting.screen import (
    ONSET_GRID,
    ONSET_GRID_DYNAMIC,
    Screen,
    init_from,
    spec_for,
    warm_from,
)
from jaxcal.diagnosis.kinds.linearization import Linearization
from jaxcal.diagnosis.kinds.onsets import polish_onsets, refine_onsets
from jaxcal.diagnosis.kinds.table import Candidate, nests
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
    # forms tried: without "units" every effect is fleet-wide or on every unit
    # (steps need the per-unit form and are left out)
    forms: tuple[str, ...] = ("fleet", "units")

    def __post_init__(self):
        if self.top_k < 1 or self.pair_top < 0 or not 0 < self.alpha < 1:
            raise ValueError(
                "IdentifyConfig: need top_k >= 1, pair_top >= 0, 0 < alpha < 1"
            )
        if not self.forms or not set(self.forms) <= {"fleet", "units"}:
            raise ValueError("IdentifyConfig.forms: a subset of ('fleet', 'units')")


class Identification(NamedTuple):
    """Outcome of :func:`identify`."""

    null: FitResult
    ranking: list[RankEntry]  # best first
    winner: RankEntry | None  # significant best model, or None
    winner_fit: FitResult | None
    confounded: list[str]  # effects confounded with the winner (winner first)
    absorbed: list[str]  # effects the declared parameters can mimic
    num_tests: int
    # entry name -> FitResult of every refitted model, the winner's whole, the others
    # with what a noise refit reads (_slim); released once the noise passes are done
    fits: dict
    onset_ci: dict  # candidate key -> [U, 2] rows of a step's onset interval
    # the candidate no unit showed on its own with the largest summed unit score, on
    # every unit, and that sum: a basis for the noise model (pipeline), never a verdict
    near_miss: tuple = ()  # (Candidate, LR) or ()


def _profile_onsets(model, data, declared, members, fit, offset, cfg):
    """``(members, fit, intervals)`` with every per-unit step's onsets profiled at
    the fitted point (:mod:`jaxcal.diagnosis.kinds.onsets`) and the model refitted
    when one moved."""
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


def _pairs_to_test(screen: Screen, singles, cfg: IdentifyConfig) -> list[tuple]:
    """Pairs of the best ``pair_top`` effects (the best form of each, ``singles``
    sorted by BIC) whose members do not reproduce each other's signature."""
    top = []
    for e in singles:  # the best form of each of the best effects
        if all(e.members[0].name != t.members[0].name for t in top):
            top.append(e)
        if len(top) >= cfg.pair_top:
            break
    return [
        (a.members[0], b.members[0])
        for a, b in itertools.combinations(top, 2)
        if max(screen.overlap(a.members[0], b.members[0]),
               screen.overlap(b.members[0], a.members[0])) < cfg.confound_r2
    ]  # fmt: skip


@dataclasses.dataclass
class _Refits:
    """Joint nonlinear refits of ranked entries with the declared parameters: each
    replaces its linearised entry in ``entries`` and keeps its fit and the profiled
    onset intervals of its steps."""

    model: Model
    data: LoopData
    declared: Sequence[str]
    null: FitResult
    offset: np.ndarray | None
    cfg: IdentifyConfig
    entries: dict  # entry name -> RankEntry, updated in place
    fits: dict = dataclasses.field(default_factory=dict)  # entry name -> FitResult
    onset_ci: dict = dataclasses.field(default_factory=dict)  # name -> {step: [U, 2]}
    warm: dict = dataclasses.field(default_factory=dict)  # name -> an earlier fit
    # the screen's linearisation at null with every derivative (Screen.null_lin)
    null_lin: Linearization | None = None
    slimmed: set = dataclasses.field(default_factory=set)  # fits already slim
    basis: bool = True  # a slimmed fit keeps what a noise refit reads (_slim)

    def _start(self, name: str, spec):
        """Where the refit of ``name`` starts: where its earlier fit ended, else at
        the declared-only solution with the effects at zero; either point's
        linearisation kept (:func:`.joint.resume_at`), so its first evaluation
        costs none."""
        # taken out: the caller handed the earlier fits over, and each is released
        # once its refit has started (bounds the memory)
        model, data, prev = self.model, self.data, self.warm.pop(name, None)
        init = None if prev is None else warm_from(prev, model, data, spec)
        if init is None:
            # the screen's linearisation of the declared-only point has every
            # candidate's derivatives; the refits between evict it from the cache
            resume_at(model, data, self.null, self.null_lin)
            return init_from(self.null, model, data, spec)
        resume_at(model, data, prev)
        return init

    def refit(self, members) -> None:
        """Refit ``members`` and replace their entry."""
        model, data, null = self.model, self.data, self.null
        spec = spec_for(self.declared, members, null.spec.initial_state)
        name = " + ".join(c.label for c in members)
        fit = fit_model(
            model, data, spec, self._start(name, spec), offset=self.offset,
            max_iters=self.cfg.max_iters,
        )  # fmt: skip
        members, fit, self.onset_ci[name] = _profile_onsets(
            model, data, self.declared, members, fit, self.offset, self.cfg
        )
        self.fits[name] = fit
        sizes, stds = effect_sizes(fit, members, data)
        old = self.entries[name]
        self.entries[name] = rank_entry(members, null.ssr - fit.ssr, null, data, sizes,
                                    stds, True, old.detectability)  # fmt: skip
        self._slim_losers()

    def _slim_losers(self) -> None:
        """Slim (:func:`_slim`) every fit but the two :func:`_winner` can pick: the
        refitted entry and the refitted single of lowest BIC. An entry is refitted
        once, so a fit that falls behind never comes back."""
        refitted = [self.entries[n] for n in self.fits]
        singles = [e for e in refitted if len(e.members) == 1]
        keep = {e.name for e in refitted if not np.isfinite(e.bic)}  # never guess
        for group in (refitted, singles):
            if group:  # every entry at the lowest BIC (a tie is the winner's to break)
                low = min(e.bic for e in group)
                keep |= {e.name for e in group if e.bic == low}
        for name in set(self.fits) - keep - self.slimmed:
            made = (self.model, self.data) if self.basis else None
            self.fits[name] = _slim(self.fits[name], made)
            self.slimmed.add(name)


def _slim(fit: FitResult, made: tuple | None) -> FitResult:
    """``fit`` with only what the noise model's refit on it reads
    (:func:`.pipeline._noise_basis`): the residual, the entries used and the raw
    signatures of the per-unit columns (``made``: the model and data of the fit, a
    static model's made again from its Jacobians when read; ``None``: no noise
    refit will read them), and the model's linearisation at its end point (its
    outputs and its own few derivatives: the next pass's refit starts there,
    :meth:`_Refits._start`). The prewhitened columns, the outputs and row inputs
    are a fleet's rows times their columns each; only its own fit and the winner's
    verdicts read them."""
    ev = fit.evaluation
    local, remake = None, None
    if made is not None:
        remake = local_remake(*made, fit)
        if remake is None:
            local = np.array(raw_columns_of(ev)[:, :, : fit.layout.num_local])  # copy
    sig = ev.sig._replace(y=None, x=None, cols=local)
    slim = ev._replace(yhat=None, white=None, theta=None, inputs=None, sig=sig,
                       cols=None, whiten=None, remake=remake)  # fmt: skip
    return fit._replace(evaluation=slim)


def warm_starts(fits: dict) -> dict:
    """``fits`` (entry name -> fit) with only what a refit started where each ended
    reads (:func:`~jaxcal.diagnosis.fitting.screen.warm_from`,
    :func:`~jaxcal.diagnosis.fitting.joint.resume_at`): its terms, coefficients and
    linearisation at its end point."""
    return {name: _slim(fit, None) for name, fit in fits.items()}


def _winner(ranking, entries: dict, fits: dict, num_tests: int, cfg: IdentifyConfig):
    """The best refitted entry when it is significant (``bic_margin`` and the
    Bonferroni p-value), a pair only when it beats the best single by the margin;
    ``None`` otherwise."""
    threshold = np.log10(cfg.alpha / max(num_tests, 1))
    winner = ranking[0] if ranking else None  # empty: no unit shows any candidate
    best_single = min(
        (e for e in entries.values() if len(e.members) == 1 and e.refit),
        key=lambda e: e.bic,
        default=None,
    )
    if winner is not None and len(winner.members) > 1 and best_single is not None:
        if winner.bic > best_single.bic - cfg.bic_margin:
            winner = best_single
    significant = (
        winner is not None
        and winner.delta_bic >= cfg.bic_margin
        and winner.log10_p < threshold
    )
    if not significant or winner.name not in fits:
        return None
    return winner


def _confounded_with(winner, singles, entries: dict, screen: Screen, cfg) -> list:
    """Candidates confounded with each member of ``winner`` (module docstring, 4):
    within the margin of it, by the BIC or the LR statistic, and reproducing at
    least ``confound_r2`` of its signature; nested candidates are not rivals."""
    confounded = []
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
    return confounded


def identify(
    model: Model,
    data: LoopData,
    declared: Sequence[str],
    library: Sequence[Candidate],
    cfg: IdentifyConfig,
    null: FitResult,
    *,
    offset: np.ndarray | None = None,
    warm: dict | None = None,
    basis: bool = True,
) -> Identification:
    """Rank the library against the residual of the declared-only fit ``null``.

    Args:
        model: the model.
        data: the rows (with their noise model).
        declared: the calibrated parameters.
        library: candidate effects (:func:`jaxcal.diagnosis.kinds.table.build_library`).
        cfg: settings.
        null: the declared-only fit (the "before" calibration).
        offset: a fixed discrepancy term included in every refit (output units).
        warm: entry name -> an earlier fit of it (the last noise pass's
            ``fits``): its refit starts where that one ended. Consumed: each
            entry is removed from the dict as its refit starts.
        basis: a fit the noise model may be refitted to is kept (``False``: no
            noise pass follows, and a fit that is not the winner's keeps no
            columns).

    Returns:
        :class:`Identification`.
    """
    screen = Screen(model, data, library, null)
    singles, onset_ci, near_miss = screened_singles(
        screen, library, null, data, cfg.forms
    )
    singles.sort(key=lambda e: e.bic)
    entries = {e.name: e for e in singles}
    pairs = _pairs_to_test(screen, singles, cfg)
    for pair in pairs:
        lr = screen.joint(pair)[0]
        e = rank_entry(pair, lr, null, data, [np.nan] * 2, [np.nan] * 2, False, 1.0)
        entries[e.name] = e
    screen.release()  # the refits read none of its columns
    refits = _Refits(model, data, declared, null, offset, cfg, entries,
                     warm={} if warm is None else warm,
                     null_lin=screen.null_lin, basis=basis)  # fmt: skip
    for e in singles[: cfg.top_k]:
        refits.refit(list(e.members))
    for pair in pairs:
        refits.refit(list(pair))
    ranking = sorted(entries.values(), key=lambda e: e.bic)
    for _ in range(cfg.top_k):  # a linearised score may have ranked a model too low
        if not ranking or ranking[0].refit:
            break
        refits.refit(list(ranking[0].members))
        ranking = sorted(entries.values(), key=lambda e: e.bic)
    num_tests = len(singles) + len(pairs)
    fits = refits.fits
    winner = _winner(ranking, entries, fits, num_tests, cfg)
    absorbed = sorted({e.members[0].name for e in singles
                       if e.detectability < cfg.absorbed_frac})  # fmt: skip
    confounded = []
    if winner is not None:
        confounded = _confounded_with(winner, singles, entries, screen, cfg)
        # the winner's onsets were profiled at its own fit
        onset_ci.update(refits.onset_ci.get(winner.name, {}))
    fits = {
        name: fit if (winner is not None and name == winner.name)
        or name in refits.slimmed else _slim(fit, (model, data) if basis else None)
        for name, fit in fits.items()
    }  # fmt: skip
    return Identification(
        null, ranking, winner, None if winner is None else fits[winner.name],
        confounded, absorbed, num_tests, fits, onset_ci, near_miss,
    )  # fmt: skip
