"""The held-out check: the trend family and noise scale a fleet's prognosis uses.

Each fold's training units are cut at random ages (a unit seen before its end, as a
test unit is), predicted by the degradation model learned on the other folds, and
scored against their known ends. Every (trend family, noise scale) pair gets a CRPS
(:func:`~jaxcal.prognosis.score.crps`: a proper score of the whole predicted
distribution, calibrated and sharp at once), a coverage and an RMSE; the choice is the
lowest CRPS among the *honest* pairs, whose held-out coverage is within two binomial
standard errors of the nominal one (if none is, the best covered, and a note says
so). ``cfg`` is a :class:`~jaxcal.prognosis.pipeline.PrognosisConfig`.
"""

from __future__ import annotations

import jax
import numpy as np

from jaxcal.prognosis import degradation
from jaxcal.prognosis.predict import predict
from jaxcal.prognosis.score import crps
from jaxcal.prognosis.trajectories import MIN_ROWS, Trajectories
from jaxcal.prognosis.trends import size

NOISE_SCALES = (1.0, 1.5, 2.0, 3.0, 5.0, 8.0)
# the trend families the held-out check chooses from (jaxcal.prognosis.trends)
TRENDS = ("poly1", "poly2", "poly3", "exp1", "exp2", "exp4")
# RUL samples per held-out unit (the check needs coverage, not tails)
CHECK_SAMPLES = 300
CHECK_CUTS = 2  # random ages per held-out training unit
# a held-out unit is cut so that this share of its life, at least, is still to come or
# already seen: a cut at the very start or the very end checks nothing
CUT_RANGE = (0.05, 0.8)


def folds_of(num: int, folds: int) -> int:
    """The folds of ``num`` units: ``folds``, or one per unit (leave one out) when the
    units kept by a fold would be too few for a trend prior."""
    folds = min(folds, num)
    if num - -(-num // folds) < degradation.MIN_UNITS:
        folds = num
    return folds


def held_out_cases(train: Trajectories, cfg):
    """Per fold: the training units kept, and the held-out units cut at random ages
    with their true RULs (step 3 of the module docstring)."""
    rng = np.random.default_rng(cfg.seed)
    num = train.unit.size
    rows = train.mask.sum(1)
    for fold in np.array_split(rng.permutation(num), folds_of(num, cfg.folds)):
        held = np.zeros(num, bool)
        held[fold] = True
        cut_units = np.repeat(fold, CHECK_CUTS)
        share = rng.uniform(*CUT_RANGE, size=cut_units.size)
        keep = np.maximum(np.round(rows[cut_units] * (1 - share)), MIN_ROWS).astype(int)
        cut = train.units(cut_units).truncated(keep)
        yield train.units(~held), cut, train.now[cut_units] - cut.now


def choose(train: Trajectories, cfg, boundary) -> dict:
    """Held-out CRPS, coverage and RMSE of each trend family and noise scale; the
    choice is the lowest CRPS (:func:`~jaxcal.prognosis.score.crps`) among the honest
    pairs (module docstring)."""
    num = train.unit.size
    if num - 1 < degradation.MIN_UNITS:
        raise ValueError(
            f"train: {num} run-to-failure unit(s); choosing the trend and noise scale "
            f"on held-out units needs at least {degradation.MIN_UNITS + 1} (or give "
            "both trend= and noise_scale=)"
        )
    kept = num - -(-num // folds_of(num, cfg.folds))  # the fewest units a fold keeps
    trends = TRENDS if cfg.trend is None else (cfg.trend,)
    fits = tuple(t for t in trends if size(t) + 1 <= kept)
    trends = fits or (min(trends, key=size),)
    scales = NOISE_SCALES if cfg.noise_scale is None else (cfg.noise_scale,)
    hits = np.zeros((len(trends), len(scales), 3))
    cases = 0
    for fold, (kept, cut, truth) in enumerate(held_out_cases(train, cfg)):
        cases += truth.size
        # every scale in one call: the cut units repeated once per scale
        each = np.tile(np.arange(truth.size), len(scales))
        batch = cut.units(each)
        per_unit = np.repeat(np.asarray(scales, float), truth.size)
        for i, trend in enumerate(trends):
            learned = degradation.fit(kept, deg_config(cfg, trend), boundary=boundary)
            pred = predict(
                learned, batch, jax.random.PRNGKey(cfg.seed + fold),
                num_samples=CHECK_SAMPLES, coverage=cfg.coverage, bands=False,
                noise_scale=per_unit,
            )  # fmt: skip
            truths = truth[each]
            inside = (truths >= pred.rul_low) & (truths <= pred.rul_high)
            for j in range(len(scales)):
                part = slice(j * truth.size, (j + 1) * truth.size)
                hits[i, j] += (
                    inside[part].sum(),
                    ((pred.rul[part] - truth) ** 2).sum(),
                    crps(pred.samples[part], truth).sum(),
                )
    coverage, rmse = hits[..., 0] / cases, np.sqrt(hits[..., 1] / cases)
    mean_crps = hits[..., 2] / cases
    # honest: held-out coverage within two binomial standard errors of the nominal
    slack = 2.0 * np.sqrt(cfg.coverage * (1.0 - cfg.coverage) / cases)
    honest = coverage >= cfg.coverage - slack
    pick = np.where(honest, mean_crps, np.inf) if honest.any() else -coverage
    i, j = np.unravel_index(np.argmin(pick), pick.shape)
    return {
        "trends": list(trends),
        "scales": list(scales),
        "crps": mean_crps.tolist(),
        "coverage": coverage.tolist(),
        "rmse": rmse.tolist(),
        "honest": honest.tolist(),
        "trend": trends[i],
        "noise_scale": float(scales[j]),
        "cases": int(cases),
    }


def notes(check: dict, cfg) -> list[str]:
    if "honest" not in check or np.any(check["honest"]):
        return []
    best = max(max(row) for row in check["coverage"])
    return [
        f"no trend and noise scale reached the nominal {cfg.coverage:.0%} coverage on "
        f"held-out training units (at best {best:.2f}): the intervals are too narrow "
        "(a biased calibration, or test units unlike the training ones)"
    ]


def deg_config(cfg, trend: str) -> degradation.DegradationConfig:
    return degradation.DegradationConfig(trend=trend, max_tightness=cfg.max_tightness)
