"""experiments/policy_turbofan.py's subset of the test units and its effects."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
from policy_turbofan import (  # noqa: E402
    TURBOFAN_EFFECTS,
    bench_rows_of,
    windows,
    with_effect,
)

from jaxcal.data.padded import Padded  # noqa: E402


def _units(lengths=(10, 14)) -> Padded:
    steps = max(lengths)
    t = np.arange(steps, dtype=float)
    x = np.stack([np.stack([t + 100 * u, -t], axis=1) for u in range(len(lengths))])
    return Padded(
        w=x[..., :1].copy(), x=x, theta=x[..., :1] / 1000,
        lengths=np.asarray(lengths, np.int32), unit_ids=np.asarray([7, 8]),
    )  # fmt: skip


def test_windows_are_each_units_first_and_last_rows():
    out = windows(_units(), 4)
    assert out.unit_ids.tolist() == [7, -7, 8, -8] and out.lengths.tolist() == [4] * 4
    np.testing.assert_array_equal(out.x[1, :, 0], [6, 7, 8, 9])  # unit 7's last
    np.testing.assert_array_equal(out.x[3, :, 0], [110, 111, 112, 113])
    with pytest.raises(ValueError, match=r"test units \[7\] have fewer than"):
        windows(_units(), 6)


def test_effects_start_a_third_in_on_the_chosen_output_only():
    x = np.ones((2, 9, 3))
    sd = np.array([0.5, 1.0, 2.0])
    rng = np.random.default_rng(0)
    bias = with_effect(x, 1, sd, "bias", 3.0, rng) - x
    assert np.all(bias[:, :3] == 0) and np.all(bias[:, 3:, 1] == 3.0)
    assert np.all(bias[..., [0, 2]] == 0)
    drift = with_effect(x, 2, sd, "drift", 4.0, rng) - x
    np.testing.assert_allclose(drift[0, 3:, 2], np.linspace(0, 8.0, 6))
    gain = with_effect(2 * x, 0, sd, "gain", 3.0, rng) / (2 * x)
    np.testing.assert_allclose(gain[:, 3:, 0], 1 + 3 * 0.5 / 2)
    ar = with_effect(x, 0, sd, "ar1", 0.8, rng) - x
    assert np.all(ar != 0) and np.all(x == 1)  # every output, a copy
    assert np.array_equal(with_effect(x, 0, sd, "none", 0.0, rng), x)
    with pytest.raises(ValueError, match="unknown effect kind 'step'"):
        with_effect(x, 0, sd, "step", 1.0, rng)


def test_bench_rows_spread_over_each_units_life():
    w, x = bench_rows_of(_units(), 4, 5)
    assert w.shape == (4, 5, 1) and x.shape == (4, 5, 2)
    assert x[:, 0, 0].tolist() == [0, 5, 100, 109]  # each unit's start and end


def test_white_noise_is_an_ar1_of_coefficient_zero_at_the_declared_std():
    assert TURBOFAN_EFFECTS["white 1σ"] == ("ar1", 0.0)
    x = np.zeros((4, 4000, 2))
    sd = np.array([0.5, 2.0])
    e = with_effect(x, 0, sd, "ar1", 0.0, np.random.default_rng(1))
    np.testing.assert_allclose(e.std(axis=(0, 1)), sd, rtol=0.03)
    lag1 = np.mean(e[:, 1:] * e[:, :-1], axis=(0, 1)) / e.var(axis=(0, 1))
    assert np.all(np.abs(lag1) < 0.03)
    coloured = with_effect(x, 0, sd, "ar1", 0.8, np.random.default_rng(1))
    lag1 = np.mean(coloured[:, 1:] * coloured[:, :-1]) / coloured.var()
    assert abs(lag1 - 0.8) < 0.05
