"""``prognose``: calibrate a fleet, learn how its units degrade, predict their RUL.

The steps, each timed in :attr:`Prognosis.timings`:

1. **calibrate** the run-to-failure units (``train``) and the units in service
   (``test``) with any method of :func:`jaxcal.calibrate` (the UKF by default), in one
   call: one compiled program runs both fleets, with one noise (given, or estimated
   on both), so that their trajectories are filtered alike.
2. **learn** the fleet's degradation (:mod:`jaxcal.prognosis.degradation`): the trend
   prior and the failure boundaries from the training units' ends.
3. **check the intervals on held-out training units**: each fold's units are cut at
   random ages and predicted from the other folds; the trend family and noise scale
   are those of the lowest held-out CRPS among the honest pairs, unless given
   (:mod:`jaxcal.prognosis.check`).
4. **predict** (:mod:`jaxcal.prognosis.predict`).

:func:`prognose_trajectories` runs steps 2-4 on trajectories from anywhere.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence

import jax
import numpy as np

from jaxcal.calibrators.front.door import calibrate
from jaxcal.data.dataset import Dataset
from jaxcal.data.readers import read_dataset
from jaxcal.models import load
from jaxcal.prognosis import check as held_out
from jaxcal.prognosis import degradation
from jaxcal.prognosis.predict import RulPrediction, predict
from jaxcal.prognosis.trajectories import MIN_ROWS, Trajectories, from_arrays
from jaxcal.prognosis.trends import check_trend


@dataclasses.dataclass(frozen=True)
class PrognosisConfig:
    method: str = "ukf"  # the calibration method (any of jaxcal.calibrate's)
    coverage: float = 0.9  # nominal coverage of the RUL interval
    samples: int = 1000  # RUL samples per test unit
    # the trend family (jaxcal.prognosis.trends) and the noise scale; None: chosen on
    # held-out training units (module docstring)
    trend: str | None = None
    noise_scale: float | None = None
    max_tightness: float = 0.35  # see degradation.DegradationConfig
    folds: int = 5  # held-out folds of the training units
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class Prognosis:
    """What :func:`prognose` found (module docstring)."""

    prediction: RulPrediction
    model: degradation.DegradationModel
    train: Trajectories
    test: Trajectories
    noise_check: dict
    timings: dict
    notes: tuple[str, ...]


def _boundary_notes(model: degradation.DegradationModel) -> list[str]:
    """A declared limit the training units' calibrated ends do not reach (or pass):
    the calibration lags or is biased there, and the RULs with it; training units no
    learned boundary marks: a failure the calibrated parameters do not see."""
    notes = []
    if not model.declared.any():
        carried = model.carriers[:, model.decides].any(axis=1)
        if not carried.all():
            notes.append(
                f"{int((~carried).sum())} of {carried.size} training units end far "
                "from every deciding boundary: they failed by a mode the calibrated "
                "parameters do not show (calibrate its parameters, theta=)"
            )
        split = [
            f"{n} ({int(c)} of {carried.size})"
            for n, c, d in zip(
                model.names, model.carriers.sum(0), model.decides, strict=True
            )
            if d and c < carried.size
        ]
        if split:
            notes.append(
                "boundaries learned from the units that degraded in them (the others "
                f"failed by another mode): {', '.join(split)}"
            )
        if len(model.modes) > 1:
            modes = "; ".join(
                f"{', '.join(n for n, c in zip(model.names, m, strict=True) if c)} "
                f"({w:.0%})"
                for m, w in zip(model.modes, model.mode_weight, strict=True)
            )
            notes.append(
                f"the trend prior is a mixture of {len(model.modes)} fault modes, each "
                f"one Gaussian over its units (the parameters it carries, its share): "
                f"{modes}"
            )
    for p in np.flatnonzero(model.declared):
        mean, std = model.end_mean[p], model.end_std[p]
        if abs(model.boundary[p] - mean) > 2.0 * std:
            notes.append(
                f"the training units end at a calibrated {model.names[p]} of "
                f"{mean:.4g} +- {std:.2g}, not at the declared "
                f"{model.boundary[p]:.4g}: "
                "the calibrated estimate lags or is biased there, so the RULs are too "
                "long or too short (without boundary= the limit is learned from the "
                "calibrated ends)"
            )
    return notes


def prognose_trajectories(
    train: Trajectories,
    test: Trajectories,
    boundary: Mapping[str, float] | None = None,
    config: PrognosisConfig = PrognosisConfig(),
    *,
    timings: dict | None = None,
    notes: Sequence[str] = (),
) -> Prognosis:
    """Steps 2-4 of the module docstring on calibrated trajectories."""
    if tuple(test.names) != tuple(train.names):
        raise ValueError(
            f"test trajectories of {list(test.names)}, training ones of "
            f"{list(train.names)}: expected the same parameters"
        )
    timings = dict(timings or {})
    start = time.perf_counter()
    if config.trend is not None:
        check_trend(config.trend)
    if config.trend is not None and config.noise_scale is not None:
        degradation.require_units(train.unit.size, config.trend)
        check = {"trend": config.trend, "noise_scale": float(config.noise_scale)}
    else:
        degradation.require_units(train.unit.size, "poly1")
        check = held_out.choose(train, config, boundary)
    timings["check"] = time.perf_counter() - start
    start = time.perf_counter()
    model = degradation.fit(
        train, held_out.deg_config(config, check["trend"]), boundary,
        noise_scale=check["noise_scale"],
    )  # fmt: skip
    timings["learn"] = time.perf_counter() - start
    start = time.perf_counter()
    pred = predict(
        model, test, jax.random.PRNGKey(config.seed),
        num_samples=config.samples, coverage=config.coverage,
    )  # fmt: skip
    timings["predict"] = time.perf_counter() - start
    notes = list(notes) + held_out.notes(check, config) + _boundary_notes(model)
    censored = int((pred.censored > 0.5).sum())
    if censored:
        notes.append(
            f"{censored} unit(s) cross no boundary within the horizon in most samples: "
            "their RUL is the horizon, a lower bound"
        )
    return Prognosis(pred, model, train, test, check, timings, tuple(notes))


def prognose(
    model,
    train,
    test,
    theta: Sequence[str] | None = None,
    noise=None,
    boundary: Mapping[str, float] | None = None,
    config: PrognosisConfig = PrognosisConfig(),
    *,
    outputs: Sequence[str] | None = None,
    progress: bool = True,
) -> Prognosis:
    """Calibrate ``train`` (run to failure) and ``test`` (in service), then predict.

    Args:
        model: a :class:`~jaxcal.model.Model` or a ``jaxcal.models.load`` spec.
        train, test: paths or :class:`~jaxcal.data.dataset.Dataset` s; every training
            unit's last row is its end of life.
        theta: the calibrated health parameters (default: all the model's).
        noise: as :func:`jaxcal.calibrate`'s (default: estimated on both fleets).
        boundary: parameter -> declared failure limit (default: learned).
        config: :class:`PrognosisConfig`.
        outputs: the outputs to calibrate on (default: every one in the data).
        progress: progress lines on stderr.
    """
    model = load(model)
    timings = {}
    start = time.perf_counter()
    both, shift, num_train = _one_fleet(model, train, test, outputs)
    cal = calibrate(
        model, both, config.method, theta, noise, seed=config.seed, progress=progress
    )
    timings["calibrate"] = time.perf_counter() - start
    notes = [f"calibration: {n}" for n in cal.notes]
    if cal.notes:
        notes.append(
            "(the calibration ran both fleets at once: test unit u is unit "
            f"u + {shift} in its notes)"
        )
    rows = {"train": slice(0, num_train), "test": slice(num_train, None)}
    traj = {
        part: from_arrays(
            cal.unit[sl] - (shift if part == "test" else 0),
            cal.time[sl],
            cal.theta[sl],
            cal.theta_names,
            std=None if cal.theta_std is None else cal.theta_std[sl],
            valid=cal.valid[sl],
            label=part,
            min_rows=1 if part == "test" else MIN_ROWS,
        )  # fmt: skip
        for part, sl in rows.items()
    }
    return prognose_trajectories(
        traj["train"], traj["test"], boundary, config, timings=timings, notes=notes
    )


def _one_fleet(model, train, test, outputs):
    """``(data, shift, rows of train)``: the training and test units as one data set
    (test unit ids shifted by ``shift`` past the training ones), so that one compiled
    calibration runs both fleets in one batch, with one noise estimate."""
    a = read_dataset(train, model).for_model(model, outputs)
    b = read_dataset(test, model).for_model(model, a.output_names)
    shift = int(a.unit.max()) + 1 - int(b.unit.min())
    both = Dataset(
        w=np.concatenate([a.w, b.w]),
        x=np.concatenate([a.x, b.x]),
        condition_names=a.condition_names,
        output_names=a.output_names,
        unit=np.concatenate([a.unit, b.unit + shift]),
        time=np.concatenate([a.time, b.time]),
        source=f"{a.source} + {b.source}",
    )
    return both, shift, a.num_rows
