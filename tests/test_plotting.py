"""Plotting helpers write real PNG files atomically and reject malformed input."""

import numpy as np
import pytest

from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES
from jaxcal.plotting import (
    plot_flight_profiles,
    plot_health_trajectories,
    plot_stacked_traces,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _assert_png(path, directory):
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC) and len(data) > 1000
    # atomic write: no temporary file is left next to the figure
    assert sorted(p.name for p in directory.iterdir()) == [path.name]


def test_plot_flight_profiles_writes_png(tmp_path):
    t = np.arange(50) * 10.0
    w = np.stack(
        [
            10_000 + 400 * t / 10,
            0.4 + 0.005 * t / 10,
            np.full(50, 80.0),
            np.full(50, 480.0),
        ],
        axis=-1,
    )
    batch = np.stack([w, w * [1.0, 1.0, 0.9, 1.0]])
    mask = np.ones((2, 50), bool)
    mask[1, 40:] = False
    out = tmp_path / "sub" / "profile.png"  # the directory is created on demand
    assert plot_flight_profiles(out, t, batch, mask=mask, labels=["a", "b"]) == str(out)
    _assert_png(out, out.parent)
    with pytest.raises(ValueError, match="labels"):
        plot_flight_profiles(tmp_path / "x.png", t, batch, labels=["only one"])
    with pytest.raises(ValueError, match="w must have"):
        plot_flight_profiles(tmp_path / "x.png", t, w[:, 0])


def test_plot_health_trajectories_writes_png(tmp_path):
    cycles = np.tile(np.arange(1, 31), (3, 1))
    theta = np.zeros((3, 30, 10))
    theta[..., 6] = -1e-4 * cycles * np.array([[1.0], [1.5], [2.0]])
    mask = cycles <= np.array([[30], [25], [20]])
    out = tmp_path / "theta.png"
    plot_health_trajectories(
        out, cycles, theta, HEALTH_NAMES, mask=mask, onset=[10, 12, 8]
    )
    _assert_png(out, tmp_path)
    with pytest.raises(ValueError, match="names"):
        plot_health_trajectories(tmp_path / "x.png", cycles, theta, HEALTH_NAMES[:3])
    with pytest.raises(ValueError, match="unknown name"):
        plot_health_trajectories(
            tmp_path / "x.png", cycles, theta, HEALTH_NAMES, select=("HPT_eta",)
        )


def test_plot_stacked_traces_writes_png(tmp_path):
    truth = np.repeat(np.linspace(0.0, -0.01, 4), 25)[:, None] * [1.0, 2.0]
    rng = np.random.default_rng(0)
    estimate = truth + 1e-4 * rng.standard_normal(truth.shape)
    out = tmp_path / "stacked.png"
    plot_stacked_traces(
        out,
        {"CLAC": estimate, "UKF": estimate[::-1]},
        truth=truth,
        unit_boundaries=[25, 50, 75],
        names=["HPT_eff_mod", "HPT_flow_mod"],
        max_points=40,
    )
    _assert_png(out, tmp_path)
    with pytest.raises(ValueError, match="same"):
        plot_stacked_traces(tmp_path / "x.png", {"CLAC": estimate[:10]}, truth=truth)
    with pytest.raises(ValueError, match="at least one"):
        plot_stacked_traces(tmp_path / "x.png", {})
