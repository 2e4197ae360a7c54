"""The one padded container: a Record's and a Dataset's units as padded streams."""

import jax
import numpy as np
import pytest

from jaxcal.data.dataset import Dataset
from jaxcal.data.padded import Padded
from jaxcal.models.turbofan.data.record import Record


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


def test_record_pads_by_unit_with_mask_and_edge_values():
    rec = make_record()
    padded = rec.padded()
    assert padded.x.shape == (3, 4, 3) and padded.w.shape == (3, 4, 4)
    np.testing.assert_array_equal(padded.unit_ids, [1, 2, 3])
    np.testing.assert_array_equal(padded.lengths, [4, 3, 2])
    np.testing.assert_array_equal(
        padded.mask, [[1, 1, 1, 1], [1, 1, 1, 0], [1, 1, 0, 0]]
    )
    assert padded.num_samples == rec.num_rows and padded.rows is None
    # Unit 1 holds file rows 2..5 in order; unit 3 rows 0, 1 then its last row again.
    np.testing.assert_array_equal(padded.x[0], rec.x[2:6])
    np.testing.assert_array_equal(padded.x[2], rec.x[[0, 1, 1, 1]])
    np.testing.assert_array_equal(padded.theta[1], rec.theta[[6, 7, 8, 8]])
    np.testing.assert_array_equal(padded.cycle[1], [1, 2, 3, 3])
    assert padded.x.dtype == np.float64
    assert rec.padded(np.float32).w.dtype == np.float32


def test_record_pads_to_max_len_never_truncates_and_zeros_missing_theta():
    padded = make_record(with_theta=False).padded(max_len=6)
    assert padded.x.shape == (3, 6, 3)
    np.testing.assert_array_equal(padded.lengths, [4, 3, 2])
    assert padded.theta.shape == (3, 6, 10) and not np.any(padded.theta)
    with pytest.raises(ValueError, match="max_len=3 is shorter than a unit of 4"):
        make_record().padded(max_len=3)
    with pytest.raises(ValueError, match="at least one row"):
        make_record().take(slice(0, 0)).padded()


def test_dataset_padding_maps_back_to_rows():
    data = Dataset(
        w=np.arange(10.0)[:, None], x=np.arange(10.0)[:, None] * 2,
        condition_names=("a",), output_names=("b",),
        unit=[7, 7, 3, 7, 3, 3, 3, 7, 9, 7], time=np.arange(10.0)[::-1],
    )  # fmt: skip
    padded = data.padded()
    np.testing.assert_array_equal(padded.unit_ids, [7, 3, 9])
    np.testing.assert_array_equal(padded.lengths, [5, 4, 1])
    # rows of a unit in time order (descending row here), padding repeats the last
    np.testing.assert_array_equal(padded.rows[0], [9, 7, 3, 1, 0])
    np.testing.assert_array_equal(padded.rows[2], [8, -1, -1, -1, -1])
    np.testing.assert_array_equal(padded.w[2, :, 0], [8.0] * 5)
    np.testing.assert_array_equal(padded.to_rows(padded.x, 10), data.x)


def test_padded_is_a_pytree_jitted_code_takes_whole():
    padded = make_record().padded()

    @jax.jit
    def valid_mean(p: Padded):
        weight = p.mask[..., None]
        return (p.x * weight).sum((0, 1)) / weight.sum()

    np.testing.assert_allclose(valid_mean(padded), make_record().x.mean(0), rtol=1e-12)
