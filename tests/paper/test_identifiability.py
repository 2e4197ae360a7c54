"""The weakest-direction analysis on a linear stand-in with a built-in blind spot."""

import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct
from support.paper_problem import paper_problem

from jaxcal.data.padded import Padded
from jaxcal.models.turbofan.physics.constants import (
    HEALTH_NAMES,
    SENSOR_NAMES,
    health_index,
    sensor_index,
)
from jaxcal.paper.identifiability import (
    identifiability_study,
    split_error,
    weak_directions,
)

SENSORS = ("T24", "T30", "T48", "Nc")
THETA = ("HPT_eff_mod", "LPT_flow_mod")
EPS = 1e-3  # how much the blind combination still moves the sensors


@struct.dataclass
class BlindEngine:
    """x = A theta (+ w): LPT flow acts like -2 x HPT efficiency, up to EPS."""

    a: jnp.ndarray  # [28, 10]

    def evaluate(self, w, theta):
        x = theta @ self.a.T + jnp.sum(w) * 1e-3
        return x * jnp.where(w[0] < 0, jnp.nan, 1.0), None  # w[0] < 0: no solution


def _setup(num_units=3, steps=6):
    rng = np.random.default_rng(0)
    a = rng.normal(0, 1, (len(SENSOR_NAMES), len(HEALTH_NAMES)))
    i, j = health_index(list(THETA))
    s = sensor_index(list(SENSORS))
    wiggle = rng.normal(0, 1, len(SENSOR_NAMES))
    a[:, j] = -2.0 * a[:, i] + EPS * wiggle  # the blind spot: (1, 0.5) / |.|
    problem = paper_problem(
        "toy", SENSORS, THETA, np.full(2, -0.02), np.zeros(2), np.zeros(4), np.ones(4)
    )
    theta = rng.uniform(-0.02, 0.0, (num_units, 1, 2)).repeat(steps, axis=1)
    units = Padded(
        w=rng.uniform(1.0, 2.0, (num_units, steps, 4)),
        x=np.zeros((num_units, steps, 4)),
        theta=theta,
        lengths=np.full(num_units, steps, np.int32),
        unit_ids=np.arange(1, num_units + 1),
    )
    expected = np.array([1.0, 0.5]) / np.hypot(1.0, 0.5)
    sens_weak = np.linalg.svd(a[np.ix_(s, [i, j])], compute_uv=False)[-1]  # J fixed
    return BlindEngine(jnp.asarray(a)), problem, units, expected, sens_weak


def test_weak_direction_and_error_split_find_the_blind_spot():
    engine, problem, units, expected, sens_weak = _setup()
    truth = units.theta.reshape(-1, 2)
    # one method errs only along the blind spot, the other only across it
    along = truth + 0.004 * expected
    across = truth + 0.004 * np.array([-expected[1], expected[0]])
    out = identifiability_study(
        engine, problem, units, {"blind": along, "seen": across}
    )
    np.testing.assert_allclose(
        np.abs(out["weakest_direction_mean"]), expected, atol=1e-3
    )
    assert out["sensitivity_weakest_median"] == pytest.approx(sens_weak, rel=0.05)
    assert out["condition_median"] > 100
    blind, seen = out["methods"]["blind"], out["methods"]["seen"]
    assert blind["share_along_weakest"] == pytest.approx(1.0, abs=1e-5)
    assert seen["share_along_weakest"] == pytest.approx(0.0, abs=1e-5)
    for m in (blind, seen):  # squares add up to the total
        assert m["along_weakest"] ** 2 + m["across_weakest"] ** 2 == pytest.approx(
            m["theta_rmse"] ** 2
        )
    assert out["prior_mean_along_weakest"] > 0


def test_traces_of_the_wrong_length_and_unsolvable_points_are_named():
    engine, problem, units, _, _ = _setup()
    truth = units.theta.reshape(-1, 2)
    with pytest.raises(ValueError, match="trace of short has 17 samples, expected 18"):
        identifiability_study(engine, problem, units, {"short": truth[:17]})
    # a stride keeps every 2nd sample: the traces are compared at those
    out = identifiability_study(engine, problem, units, {"m": truth[::2]}, stride=2)
    assert out["num_samples"] == 9 and out["methods"]["m"]["theta_rmse"] == 0.0
    bad = units._replace(w=units.w.copy())
    bad.w[1, 2, 0] = -1.0
    with pytest.raises(ValueError, match="no finite Jacobian at 1 of 18 samples"):
        identifiability_study(engine, problem, bad, {"m": truth})


def test_weak_directions_and_split_on_a_diagonal_matrix():
    jac = np.tile(np.diag([3.0, 0.1])[None], (4, 1, 1))  # two units of 2 samples
    eig, vmin = weak_directions(jac, np.array([0, 2]))
    np.testing.assert_allclose(eig, [[0.01, 9.0], [0.01, 9.0]])
    np.testing.assert_allclose(np.abs(vmin), [[0.0, 1.0], [0.0, 1.0]])
    err = split_error(
        np.array([[0.0, 2.0]] * 4), np.zeros((4, 2)), vmin, np.array([0, 2])
    )
    assert err["share_along_weakest"] == pytest.approx(1.0)
    assert err["theta_rmse"] == pytest.approx(np.sqrt(2.0))
