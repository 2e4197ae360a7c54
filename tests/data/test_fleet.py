"""Padding a Record into per-unit arrays, and masked normalisation statistics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.data.fleet import denormalise, fit_norm_stats, normalise, to_fleet
from jaxcal.data.record import Record


def make_record(with_theta=True) -> Record:
    """Units 3, 1, 2 (file order) with 2, 4, 3 rows; column 1 of x is constant."""
    units, lengths = [3, 1, 2], [2, 4, 3]
    unit = np.repeat(units, lengths)
    cycle = np.concatenate([np.arange(1, n + 1) for n in lengths])
    n = len(unit)
    row = np.arange(n, dtype=float)
    x = np.stack([100 * unit + row, np.full(n, 518.67), -row], axis=1)
    return Record(
        w=np.stack([1000 * row, 0.01 * row, 50 + row, 480 + row], axis=1),
        x=x,
        x_names=("T24", "P2", "Nf"),
        theta=np.tile(row[:, None], (1, 10)) * 1e-3 if with_theta else None,
        unit=unit,
        cycle=cycle,
        flight_class=np.ones(n),
        hs=np.ones(n),
        rul=np.zeros(n, int),
    )


def test_to_fleet_pads_by_unit_with_mask_and_edge_values():
    rec = make_record()
    fleet = to_fleet(rec)
    assert fleet.x.shape == (3, 4, 3) and fleet.w.shape == (3, 4, 4)
    np.testing.assert_array_equal(fleet.unit_ids, [1, 2, 3])
    np.testing.assert_array_equal(fleet.lengths, [4, 3, 2])
    np.testing.assert_array_equal(
        fleet.mask, [[1, 1, 1, 1], [1, 1, 1, 0], [1, 1, 0, 0]]
    )
    assert fleet.x_names == ("T24", "P2", "Nf") and fleet.has_theta
    # Unit 1 holds file rows 2..5 in order; unit 3 rows 0, 1 then its last row again.
    np.testing.assert_array_equal(fleet.x[0], rec.x[2:6])
    np.testing.assert_array_equal(fleet.x[2], rec.x[[0, 1, 1, 1]])
    np.testing.assert_array_equal(fleet.theta[1], rec.theta[[6, 7, 8, 8]])
    np.testing.assert_array_equal(fleet.cycle[1], [1, 2, 3, 3])
    assert fleet.x.dtype == jnp.float64  # tests run with x64


def test_to_fleet_truncates_to_max_len_and_zeros_missing_theta():
    fleet = to_fleet(make_record(with_theta=False), max_len=3)
    assert fleet.x.shape == (3, 3, 3) and not fleet.has_theta
    np.testing.assert_array_equal(fleet.lengths, [3, 3, 2])
    assert fleet.theta.shape == (3, 3, 10) and not np.any(fleet.theta)
    with pytest.raises(ValueError, match="max_len"):
        to_fleet(make_record(), max_len=0)
    with pytest.raises(ValueError, match="at least one row"):
        to_fleet(make_record().take(slice(0, 0)))


@pytest.mark.parametrize("transform", [lambda f: f, jax.jit])
def test_norm_stats_use_valid_rows_only_and_invert(transform):
    rec = make_record()
    fleet = to_fleet(rec, max_len=6)  # lots of padding that must not count
    stats = transform(fit_norm_stats)(fleet)
    np.testing.assert_allclose(stats.x_mean, rec.x.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(stats.w_std, rec.w.std(axis=0), rtol=1e-12)
    # The constant column gets the floored std, not zero.
    np.testing.assert_allclose(stats.x_std[1], 1e-6 * 518.67, rtol=1e-12)
    normed = transform(normalise)(fleet, stats)
    valid = np.asarray(normed.x)[np.asarray(fleet.mask)]
    np.testing.assert_allclose(valid.mean(axis=0), 0.0, atol=1e-9)
    np.testing.assert_allclose(valid[:, [0, 2]].std(axis=0), 1.0, rtol=1e-9)
    back = transform(denormalise)(normed, stats)
    np.testing.assert_allclose(back.x, fleet.x, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(back.w, fleet.w, rtol=1e-12, atol=1e-9)
