"""Model evaluations reused across nearby points (diagnosis.kinds.linearization).

An evaluation that differs from a kept one (with the derivatives it wants) on a few
rows evaluates those rows alone (the onset polish of a step moves one row per carrier
at a time, and the refit at the moved onsets starts there); the
result must be the full evaluation's (started, as the diagnosis starts it, at the kept
point's solution), bit for bit, or the diagnosis's numbers move.
"""

from types import SimpleNamespace

import numpy as np
import pytest

import jaxcal.diagnosis.kinds.linearization as linearization
from jaxcal.diagnosis.kinds.signatures import zero_inputs

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
    kept = linearization._linearized(engine, data, inputs, frozenset())
    moved = inputs.theta.copy()
    moved[[5, 300, 599], j] += 0.01  # one row in each chunk
    near = inputs._replace(theta=moved)
    pieced = linearization._linearized(engine, data, near, frozenset())
    assert evaluated_rows == [ROWS, 3]
    # the full evaluation a diagnosis makes there: started at the kept solution
    full = linearization.linearize(
        engine, data.w, moved, outputs=tuple(data.sensor_idx), directions=frozenset(),
        start=kept.z,
    )  # fmt: skip
    assert np.array_equal(pieced.x, full.x)  # bitwise: the numbers do not move
    assert np.array_equal(pieced.ok, full.ok)
    assert not np.array_equal(pieced.x[5], linearization._linearized(
        engine, data, inputs, frozenset()).x[5])  # fmt: skip


def test_a_point_near_a_kept_one_with_its_derivatives_evaluates_its_changed_rows(
    engine, point, evaluated_rows
):
    """The refit at a step's moved onsets starts at a point that differs from the
    fit's end on a few rows: its derivatives come from the kept point but on those
    rows, the full evaluation's to the bit."""
    data, inputs = point
    j, k = (engine.parameter_names.index(n) for n in ("HPT_eff_mod", "LPT_eff_mod"))
    wanted = frozenset({("parameter", j), ("parameter", k)})
    kept = linearization._linearized(engine, data, inputs, wanted)
    moved = inputs.theta.copy()
    moved[[5, 300, 599], j] += 0.01
    pieced = linearization._linearized(
        engine, data, inputs._replace(theta=moved), frozenset({("parameter", k)})
    )
    assert evaluated_rows == [ROWS, 3]
    full = linearization.linearize(
        engine, data.w, moved, outputs=tuple(data.sensor_idx), directions=wanted,
        start=kept.z,
    )  # fmt: skip
    assert pieced.directions == wanted
    for a, b in ((pieced.x, full.x), (pieced.jac, full.jac), (pieced.z, full.z)):
        assert np.array_equal(a, b)
    assert not np.array_equal(pieced.jac[300], kept.jac[300])


def test_missing_derivatives_or_many_changed_rows_are_evaluated_in_full(
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
    moved[: ROWS // 2 + 1, j] += 0.02  # beyond PIECED_SHARE of either kept point's
    linearization._linearized(engine, data, inputs._replace(theta=moved), frozenset())
    assert evaluated_rows == [ROWS, ROWS, ROWS]


def _programs(monkeypatch):
    """The direction counts of the compiled programs a linearisation asks for."""
    asked = []
    original = linearization._linearize_program

    def spy(model, offset_idx, directions):
        asked.append(directions)
        return original(model, offset_idx, directions)

    monkeypatch.setattr(linearization, "_linearize_program", spy)
    return asked


def test_every_derivative_of_the_turbofan_is_the_fits_program_in_buckets(
    engine, point, monkeypatch
):
    """One compiled program serves a fit's few derivatives and a screen's every one
    (a program with every direction held 0.45 GB resident): the buckets after the
    first start at the first's solution, and agree with a fit's own bucket."""
    data, inputs = point
    w, theta = data.w[:300], inputs.theta[:300]
    asked = _programs(monkeypatch)
    every = linearization.linearize(engine, w, theta)
    num_p, num_e = len(engine.parameters), len(engine.effects)
    assert set(asked) == {linearization.DIRECTION_BUCKET} and len(asked) == -(
        -(num_p + num_e + every.jac_w.shape[2]) // linearization.DIRECTION_BUCKET
    )  # fmt: skip
    assert every.ok.all() and every.z.shape == (300, engine.warm_size)
    wanted = frozenset({("parameter", 2), ("parameter", 9), ("effect", 4)})
    few = linearization.linearize(engine, w, theta, directions=wanted)
    assert np.array_equal(every.x, few.x)
    for k, (channel, index) in enumerate(sorted(wanted)):
        full = every.jac_theta if channel == "parameter" else every.jac_effects
        np.testing.assert_allclose(
            few.jac[:, :, k], full[:, :, index], rtol=1e-9, atol=1e-12
        )


def test_a_start_near_the_solution_gives_the_cold_answer(engine, point):
    """A fit's next point starts at the last one's solution (fewer Newton
    iterations): the same outputs and derivatives to the solver's tolerance, and a
    row whose start is NaN starts cold."""
    data, inputs = point
    w, theta = data.w[:300], inputs.theta[:300]
    wanted = frozenset({("parameter", 2), ("parameter", 3)})
    near = linearization.linearize(engine, w, theta, directions=wanted)
    moved = theta.copy()
    moved[:, 2] += 2e-3
    cold = linearization.linearize(engine, w, moved, directions=wanted)
    start = near.z.copy()
    start[::7] = np.nan
    warm = linearization.linearize(engine, w, moved, directions=wanted, start=start)
    assert warm.ok.all()
    np.testing.assert_allclose(warm.x, cold.x, rtol=1e-10)
    np.testing.assert_allclose(warm.jac, cold.jac, rtol=1e-7, atol=1e-10)
    assert np.array_equal(warm.x[::7], cold.x[::7])  # started cold: the same bits
    np.testing.assert_allclose(warm.z, cold.z, rtol=1e-9, atol=1e-12)


def test_a_model_without_a_warm_start_takes_every_derivative_in_one_program(
    point, monkeypatch
):
    """A model with no solver start to share (the heat exchanger) keeps one pass
    for every derivative."""
    from jaxcal.models import load

    model = load("heat_exchanger")
    assert model.warm_fn is None and model.warm_size == 0
    n = 40
    rng = np.random.default_rng(1)
    low, high = (np.asarray(b, np.float64) for b in model.condition_range)
    w = low + (high - low) * rng.uniform(0.2, 0.8, (n, len(model.conditions)))
    theta = np.tile(model.nominal, (n, 1))
    asked = _programs(monkeypatch)
    lin = linearization.linearize(model, w, theta)
    assert len(asked) == 1 and lin.z is None


def test_kept_row_inputs_hold_their_varying_columns_and_find_every_changed_row():
    """A kept point's row inputs hold the columns equal on every row once; the rows
    found changed are those where any bit differs (a signed zero, a NaN payload)."""
    rng = np.random.default_rng(1)
    old = np.zeros((50, 6))
    old[:, 1] = 0.7  # constant: kept once
    old[:, 3] = rng.standard_normal(50)  # varying
    kept = linearization._Rows.of(old)
    assert kept.varying.tolist() == [3] and kept.cols.shape == (50, 1)
    new = old.copy()
    new[4, 0] = -0.0  # a constant column, a sign bit
    new[9, 3] = np.nextafter(new[9, 3], np.inf)  # a varying column, one ulp
    new[20, 1] = np.nan
    new[33, 5] = 1e-300
    np.testing.assert_array_equal(
        np.flatnonzero(linearization._changed_rows((kept,), (new,))), [4, 9, 20, 33]
    )
    assert not linearization._changed_rows((kept,), (old.copy(),)).any()
    before = old.copy()
    old[:] = 5.0  # the caller's array written after: the kept bits are a copy
    assert not kept.changed(before).any()
    empty = linearization._Rows.of(np.zeros((0, 3)))
    assert linearization._changed_rows((empty,), (np.zeros((0, 3)),)).shape == (0,)
