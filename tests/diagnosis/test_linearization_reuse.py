"""Model evaluations reused across nearby points (diagnosis.linearization).

An output-only evaluation that differs from a kept one on a few rows evaluates those
rows alone (the onset polish of a step moves one row per carrier at a time); the
result must be the full evaluation's, bit for bit, or the diagnosis's numbers move.
"""

from types import SimpleNamespace

import numpy as np
import pytest

import jaxcal.diagnosis.linearization as linearization
from jaxcal.diagnosis.signatures import zero_inputs

ROWS = 600  # three row chunks


@pytest.fixture
def point(engine, synthetic):
    """``(data, inputs)``: 600 rows of the study's conditions, jittered parameters."""
    w = synthetic("sensor_bias").data.w
    w = np.resize(np.asarray(w, np.float64), (ROWS, w.shape[1]))
    rng = np.random.default_rng(0)
    inputs = zero_inputs(engine, ROWS, 1)
    theta = inputs.theta * (1 + 1e-3 * rng.standard_normal(inputs.theta.shape))
    data = SimpleNamespace(w=w, sensor_idx=np.arange(4))
    return data, inputs._replace(theta=theta)


def test_a_point_near_a_kept_one_evaluates_only_its_changed_rows(
    engine, point, evaluated_rows
):
    data, inputs = point
    j = engine.parameter_names.index("HPT_eff_mod")
    linearization._linearized(engine, data, inputs, frozenset())
    moved = inputs.theta.copy()
    moved[[5, 300, 599], j] += 0.01  # one row in each chunk
    near = inputs._replace(theta=moved)
    pieced = linearization._linearized(engine, data, near, frozenset())
    assert evaluated_rows == [ROWS, 3]
    full = linearization.linearize(
        engine, data.w, moved, outputs=tuple(data.sensor_idx), directions=frozenset()
    )
    assert np.array_equal(pieced.x, full.x)  # bitwise: the numbers do not move
    assert np.array_equal(pieced.ok, full.ok)
    assert not np.array_equal(pieced.x[5], linearization._linearized(
        engine, data, inputs, frozenset()).x[5])  # fmt: skip


def test_derivatives_or_many_changed_rows_are_evaluated_in_full(
    engine, point, evaluated_rows
):
    data, inputs = point
    j = engine.parameter_names.index("HPT_eff_mod")
    linearization._linearized(engine, data, inputs, frozenset())
    moved = inputs.theta.copy()
    moved[7, j] += 0.01
    linearization._linearized(
        engine, data, inputs._replace(theta=moved), frozenset({("parameter", j)})
    )
    moved = inputs.theta.copy()
    moved[: ROWS // 2 + 1, j] += 0.01  # beyond PIECED_SHARE of the rows
    linearization._linearized(engine, data, inputs._replace(theta=moved), frozenset())
    assert evaluated_rows == [ROWS, ROWS, ROWS]
