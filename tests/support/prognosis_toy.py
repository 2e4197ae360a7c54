"""A toy fleet with a known end of life for the prognosis tests: ``theta(t) = c - a
exp(t / 50) + noise`` per unit, run to the boundary ``BOUNDARY`` (training) or cut
short before it (test, with the true RUL). Plain numpy; fixed seeds."""

import dataclasses

import jax
import numpy as np

from jaxcal.prognosis.degradation import fit
from jaxcal.prognosis.predict import predict
from jaxcal.prognosis.trajectories import from_arrays

BOUNDARY = 0.0  # theta falls from about 1 to here
NOISE = 0.01


def fleet(num_units: int, seed: int, *, cut: bool):
    """Per-row arrays of ``num_units`` units (and the true RULs when ``cut``)."""
    rng = np.random.default_rng(seed)
    unit, time, theta, truth = [], [], [], []
    for u in range(num_units):
        a = 0.02 * rng.uniform(0.8, 1.25)
        life = int(np.floor(50.0 * np.log((1.0 - BOUNDARY) / a)))  # theta(life) = 0
        stop = int(rng.uniform(0.5, 0.85) * life) if cut else life
        t = np.arange(1.0, stop + 1.0)
        unit += [u + 1] * t.size
        time.append(t)
        theta.append(1.0 - a * np.exp(t / 50.0) + NOISE * rng.standard_normal(t.size))
        truth.append(life - stop)
    names = ("health",)
    traj = from_arrays(
        unit, np.concatenate(time), np.concatenate(theta)[:, None], names
    )
    return traj, np.array(truth, np.float64)


@dataclasses.dataclass(frozen=True)
class StandIn:
    """The attributes of ``jaxcal.prognosis.pipeline.Prognosis`` the report reads."""

    prediction: object
    model: object
    train: object
    test: object
    noise_check: dict
    timings: dict
    notes: tuple[str, ...]


def prognosis(num_train: int = 8, num_test: int = 8, samples: int = 200):
    """A :class:`StandIn` prognosis of the toy fleet, and the test units' true RULs."""
    train, _ = fleet(num_train, 0, cut=False)
    test, truth = fleet(num_test, 1, cut=True)
    model = fit(train)
    pred = predict(model, test, jax.random.key(0), num_samples=samples)
    check = {"trends": ["poly3"], "scales": [1.0, 2.0], "crps": [[4.0, 3.0]],
             "coverage": [[0.8, 0.9]], "rmse": [[5.0, 5.0]], "trend": "poly3",
             "noise_scale": 2.0, "cases": 16}  # fmt: skip
    result = StandIn(
        prediction=pred, model=model, train=train, test=test, noise_check=check,
        timings={"fit": 0.1, "predict": 0.2}, notes=("a toy fleet",),
    )  # fmt: skip
    return result, truth
