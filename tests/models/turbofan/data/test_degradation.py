"""Run-to-failure degradation, factorial scenarios, row expansion and ground truth."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.models.turbofan.data.degradation import (
    DEFAULT_FACTORIAL_LEVELS,
    DegradationConfig,
    factorial_fault_scenarios,
    sample_rows,
    sample_unit_degradation,
    slice_cycles,
    theta_per_sample,
)
from jaxcal.models.turbofan.data.ground_truth import (
    DEFAULT_EOL_THETA_RANGE,
    EOL_CYCLES_BY_CLASS,
    ONSET_CYCLES_BY_CLASS,
    load_fault_ground_truth,
    summarize_ground_truth,
)
from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES, health_index

C_MAX = 104
NUM_UNITS = 30
HPT_EFF = HEALTH_NAMES.index("HPT_eff_mod")
CFG = DegradationConfig()


def _sample_batch(keys, classes):
    return jax.vmap(lambda k, c: sample_unit_degradation(k, C_MAX, CFG, c))(
        keys, classes
    )


_sample_fleet = jax.jit(chex.assert_max_traces(_sample_batch, n=1))


def _fleet(seed: int):
    keys = jax.random.split(jax.random.key(seed), NUM_UNITS)
    classes = jnp.tile(jnp.arange(1, 4), NUM_UNITS // 3)
    return keys, classes, jax.tree.map(np.asarray, _sample_fleet(keys, classes))


@pytest.fixture(scope="module")
def fleet():
    _, classes, deg = _fleet(0)
    return deg, np.asarray(classes)


def test_shapes_and_dtypes(fleet):
    deg, _ = fleet
    chex.assert_shape(deg.theta, (NUM_UNITS, C_MAX, len(HEALTH_NAMES)))
    chex.assert_shape([deg.health, deg.hs, deg.rul, deg.mask], (NUM_UNITS, C_MAX))
    chex.assert_shape([deg.eol_cycle, deg.onset_cycle], (NUM_UNITS,))
    assert deg.mask.dtype == bool and deg.hs.dtype == np.int32
    chex.assert_tree_all_finite(deg.theta)


def test_health_index_decreases_to_zero_exactly_at_eol(fleet):
    deg, _ = fleet
    for u in range(NUM_UNITS):
        eol = int(deg.eol_cycle[u])
        h = deg.health[u]
        assert 0.85 < h[0] < 1.0  # 1 - d - r with d <= 0.1
        assert np.all(np.diff(h[:eol]) < 0.0)  # strictly decreasing: no process noise
        assert h[eol - 1] == 0.0 and np.all(h[: eol - 1] > 0.0)
        np.testing.assert_array_equal(deg.mask[u], deg.cycle[u] <= eol)
        # padded cycles repeat the end-of-life state
        tail = deg.theta[u, eol:]
        np.testing.assert_array_equal(
            tail, np.broadcast_to(deg.theta[u, eol - 1], tail.shape)
        )


def test_abnormal_phase_is_steeper_with_a_smooth_onset(fleet):
    deg, _ = fleet
    for u in range(NUM_UNITS):
        eol, onset = int(deg.eol_cycle[u]), int(deg.onset_cycle[u])
        slope = -np.diff(
            deg.health[u, :eol]
        )  # slope[k] = h(k+1) - h(k+2), cycles 1-based
        before = slope[: onset - 1]
        after = slope[onset - 1 :]
        # linear normal phase: constant slope up to t_s
        np.testing.assert_allclose(before, before[0], rtol=1e-9)
        assert after.mean() > 1.8 * before.mean()
        assert np.all(np.diff(after) > 0.0)  # slope keeps growing after t_s
        # smooth transition: the first abnormal step is a small fraction of the last
        assert after[0] - before[0] < 0.5 * (after[-1] - before[0])


def test_onset_eol_hs_and_rul_follow_the_flight_class(fleet):
    deg, classes = fleet
    for u in range(NUM_UNITS):
        c = int(classes[u])
        eol, onset = int(deg.eol_cycle[u]), int(deg.onset_cycle[u])
        lo, hi = ONSET_CYCLES_BY_CLASS[c - 1]
        assert lo <= onset <= hi
        assert EOL_CYCLES_BY_CLASS[c - 1][0] <= eol <= EOL_CYCLES_BY_CLASS[c - 1][1]
        cycle = deg.cycle[u]
        np.testing.assert_array_equal(deg.hs[u], (cycle < onset).astype(np.int32))
        np.testing.assert_array_equal(deg.rul[u][:eol], eol - cycle[:eol])
        assert deg.rul[u][eol - 1] == 0 and np.all(deg.rul[u][eol:] == 0)
    assert 48 <= deg.eol_cycle.min() and deg.eol_cycle.max() <= 100


def test_theta_follows_health_loss_with_eol_magnitude_in_range(fleet):
    deg, _ = fleet
    lo, hi = DEFAULT_EOL_THETA_RANGE["HPT_eff_mod"]
    eol_theta = deg.theta[np.arange(NUM_UNITS), deg.eol_cycle - 1, HPT_EFF]
    assert np.all((lo <= eol_theta) & (eol_theta <= hi))
    # theta = m (1 - h): proportional to the health loss, initial offset m d
    ratio = deg.theta[..., HPT_EFF] / (1.0 - deg.health)
    np.testing.assert_allclose(
        ratio, eol_theta[:, None] * np.ones_like(ratio), rtol=1e-9
    )
    others = np.delete(deg.theta, HPT_EFF, axis=-1)
    assert np.all(others == 0.0)


def test_several_modifiers_and_initial_offsets():
    cfg = DegradationConfig(
        degrading=("HPT_eff_mod", "LPT_eff_mod", "LPT_flow_mod"), initial_offset=1e-3
    )
    deg = sample_unit_degradation(jax.random.key(5), 100, cfg, 3)
    cols = health_index(cfg.degrading)
    eol = int(deg.eol_cycle)
    theta = np.asarray(deg.theta)
    for j, (lo, hi) in zip(cols, cfg.theta_ranges, strict=True):
        assert lo <= theta[eol - 1, j] <= hi
    # the degrading modifiers move together (one health index)
    ratio = theta[:, cols[1]] / theta[:, cols[0]]
    np.testing.assert_allclose(ratio, ratio[-1], rtol=1e-9)
    still = np.delete(theta, cols, axis=-1)
    assert np.all(still == still[0]) and np.all((-1e-3 <= still) & (still <= 0.0))
    assert np.any(still != 0.0)


def test_determinism_and_jit_matches_eager(fleet):
    deg, classes = fleet
    keys, _, again = _fleet(0)  # also proves no retrace for new inputs
    _, _, other = _fleet(1)
    np.testing.assert_array_equal(deg.theta, again.theta)
    assert not np.allclose(deg.theta, other.theta)
    eager = sample_unit_degradation(keys[4], C_MAX, CFG, int(classes[4]))
    np.testing.assert_allclose(eager.theta, deg.theta[4], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(eager.rul, deg.rul[4])
    assert int(eager.eol_cycle) == deg.eol_cycle[4]


def test_bad_configs_raise_clear_errors():
    with pytest.raises(ValueError, match="num_cycles_max"):
        sample_unit_degradation(jax.random.key(0), 50, CFG, 1)
    with pytest.raises(ValueError, match="flight_class"):
        sample_unit_degradation(jax.random.key(0), C_MAX, CFG, 0)
    with pytest.raises(ValueError, match="unknown health parameter"):
        DegradationConfig(degrading=("HPT_efficiency",))
    with pytest.raises(ValueError, match="eol_theta_range"):
        DegradationConfig(
            degrading=("HPT_eff_mod",), eol_theta_range=((-0.02, 0.0),) * 2
        )
    with pytest.raises(ValueError, match="abnormal_exponent"):
        DegradationConfig(abnormal_exponent=(1.0, 2.0))


def test_factorial_scenarios_count_order_and_uniqueness():
    theta = np.asarray(factorial_fault_scenarios())
    assert theta.shape == (6**4, 10)
    assert np.unique(theta, axis=0).shape[0] == 6**4
    cols = health_index(list(DEFAULT_FACTORIAL_LEVELS))
    assert np.all(np.delete(theta, cols, axis=-1) == 0.0)
    assert np.all(theta[0] == 0.0)  # the healthy engine is row 0
    small = np.asarray(
        factorial_fault_scenarios(
            {"HPT_eff_mod": [0.0, -0.01], "LPT_flow_mod": [0.0, -0.01, -0.02]},
            base=np.full(10, -1e-3),
        )
    )
    j, k = HEALTH_NAMES.index("HPT_eff_mod"), HEALTH_NAMES.index("LPT_flow_mod")
    expected = [(a, b) for a in (0.0, -0.01) for b in (0.0, -0.01, -0.02)]
    np.testing.assert_allclose(small[:, [j, k]], np.array(expected) - 1e-3)
    assert np.all(np.delete(small, [j, k], axis=-1) == -1e-3)
    with pytest.raises(ValueError, match="distinct"):
        factorial_fault_scenarios({"HPT_eff_mod": [0.0, 0.0]})
    with pytest.raises(ValueError, match="unknown health parameter"):
        factorial_fault_scenarios({"HPT_eta": [0.0]})


def test_rows_hold_theta_per_flight_and_mask_padding_and_post_eol():
    cfg = DegradationConfig(eol_cycles=((50, 50),) * 3, onset_cycles=((20, 20),) * 3)
    deg = sample_unit_degradation(jax.random.key(2), 60, cfg, 2)
    chunk = slice_cycles(deg, 48, 4)  # cycles 49..52: two before EOL (50), two after
    np.testing.assert_array_equal(chunk.cycle, [49, 50, 51, 52])
    w = jnp.arange(4 * 3 * 4, dtype=float).reshape(4, 3, 4)
    sample_mask = jnp.array([[1, 1, 0], [1, 0, 0], [1, 1, 1], [1, 1, 1]], bool)
    theta, mask = theta_per_sample(chunk.theta, sample_mask)
    chex.assert_shape(theta, (12, 10))
    np.testing.assert_array_equal(theta[3:6], np.repeat(chunk.theta[1:2], 3, axis=0))
    rows = jax.jit(sample_rows)(w, sample_mask, chunk, 7, 2)
    np.testing.assert_array_equal(rows.mask, [1, 1, 0, 1, 0, 0] + [0] * 6)
    np.testing.assert_array_equal(rows.cycle, np.repeat([49, 50, 51, 52], 3))
    np.testing.assert_array_equal(rows.rul[:6], [1, 1, 1, 0, 0, 0])
    assert np.all(rows.unit == 7) and np.all(rows.fc == 2) and np.all(rows.hs == 0)
    np.testing.assert_array_equal(rows.w, np.asarray(w).reshape(12, 4))
    np.testing.assert_array_equal(rows.theta, theta)
    with pytest.raises(ValueError, match="sample_rows"):
        sample_rows(w[:, :2], sample_mask, chunk, 7, 2)


CSV = """subset,split,unit,flight_class,eol_cycle,abnormal_from_cycle,components,\
params,{}
DS01-005,dev,1,1,100,37,HPT,HPT_eff,{}
DS01-005,dev,2,3,75,19,HPT,HPT_eff,{}
DS07,test,8,1,83,35,LPT,"LPT_eff,LPT_flow",{}
"""


def _row(**deltas):
    return ",".join(str(deltas.get(n, 0.0)) for n in HEALTH_NAMES)


def test_ground_truth_loader_and_statistics(tmp_path):
    header = ",".join(f"delta_{n}" for n in HEALTH_NAMES)
    text = CSV.format(
        header,
        _row(HPT_eff_mod=-0.0166),
        _row(HPT_eff_mod=-0.0065),
        _row(LPT_eff_mod=-0.02, LPT_flow_mod=-0.03),
    )
    path = tmp_path / "gt.csv"
    path.write_text(text)
    gt = load_fault_ground_truth(path)
    assert gt.delta.shape == (3, 10) and list(gt.flight_class) == [1, 3, 1]
    stats = summarize_ground_truth(gt)
    assert stats.num_engines == 3
    assert stats.eol_delta_range["HPT_eff_mod"] == (-0.0166, -0.0065)
    assert set(stats.eol_delta_range) == {"HPT_eff_mod", "LPT_eff_mod", "LPT_flow_mod"}
    assert stats.onset_by_class == {1: (35.0, 36.0, 37.0), 3: (19.0, 19.0, 19.0)}
    assert stats.eol_by_class[1] == (83.0, 91.5, 100.0)
    hpt = summarize_ground_truth(gt, components=("HPT",))
    assert hpt.num_engines == 2 and set(hpt.eol_delta_range) == {"HPT_eff_mod"}
    with pytest.raises(ValueError, match="no engine matches"):
        summarize_ground_truth(gt, subsets=("DS09",))
    with pytest.raises(FileNotFoundError, match="missing.csv"):
        load_fault_ground_truth(tmp_path / "missing.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("subset,unit\nDS01,1\n")
    with pytest.raises(ValueError, match="missing column"):
        load_fault_ground_truth(bad)
