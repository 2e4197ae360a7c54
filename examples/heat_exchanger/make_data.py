"""A fleet of fouling heat exchangers as CSV files (the example's data).

Twelve units run 240 cycles each on a smooth, unit-specific duty schedule (hot and
cold inlet temperatures and flows). Deposits build up: ``fouling`` grows from a small
initial value at a unit-specific rate (with some acceleration), and the hot-side loss
coefficient ``dp_coeff`` grows with it as the passages narrow. ``heat_loss`` stays at
its nominal value. Sensors carry Gaussian noise. ``fleet_bias.csv`` is the same fleet
with a +0.8 K bias on the cold outlet thermometer (a miscalibrated sensor) for the
diagnosis to find.

    python examples/heat_exchanger/make_data.py [out_dir]
"""

from __future__ import annotations

import os
import sys

import jax
import numpy as np
import pandas as pd

from jaxcal.models.heat_exchanger import heat_exchanger, heat_exchanger_model

NUM_UNITS, NUM_CYCLES = 12, 240
NOISE = {"T_hot_out": 0.1, "T_cold_out": 0.1, "dp_hot": 0.2, "duty": 1.0}
BIAS = ("T_cold_out", 0.8)  # the injected sensor bias of fleet_bias.csv (K)


def _schedule(rng, n):
    """A smooth random duty schedule inside the model's valid range."""

    def smooth(low, high):
        walk = np.cumsum(rng.normal(0.0, 1.0, n))
        walk = (walk - walk.min()) / max(np.ptp(walk), 1e-9)
        return low + (high - low) * (0.15 + 0.7 * walk)

    return np.stack(
        [
            smooth(340.0, 400.0),
            smooth(280.0, 300.0),
            smooth(0.6, 2.0),
            smooth(0.6, 2.0),
        ],
        axis=1,
    )


def make_fleet(seed: int = 0) -> pd.DataFrame:
    """The clean fleet: conditions, noisy outputs, unit, time and the true θ."""
    rng = np.random.default_rng(seed)
    model = heat_exchanger_model()
    frames = []
    for unit in range(1, NUM_UNITS + 1):
        t = np.arange(NUM_CYCLES)
        rate = rng.uniform(0.4, 1.0)
        fouling = rng.uniform(0.0, 0.05) + 0.3 * rate * (t / NUM_CYCLES) ** 1.3
        dp_coeff = 10.0 * (1.0 + 1.5 * fouling)
        theta = np.stack([fouling, dp_coeff, np.full(NUM_CYCLES, 0.02)], axis=1)
        w = _schedule(rng, NUM_CYCLES)
        x = np.asarray(jax.vmap(heat_exchanger)(w, theta))
        x = x + np.array(list(NOISE.values())) * rng.standard_normal(x.shape)
        frame = pd.DataFrame(w, columns=model.condition_names)
        for j, name in enumerate(model.output_names):
            frame[name] = x[:, j]
        frame["unit"], frame["time"] = unit, t
        for j, name in enumerate(model.parameter_names):
            frame[name] = theta[:, j]
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def main(out_dir: str = "data/examples/heat_exchanger") -> tuple[str, str]:
    """Write ``fleet.csv`` and ``fleet_bias.csv``; returns their paths."""
    os.makedirs(out_dir, exist_ok=True)
    fleet = make_fleet()
    biased = fleet.copy()
    biased[BIAS[0]] += BIAS[1]
    paths = (
        os.path.join(out_dir, "fleet.csv"),
        os.path.join(out_dir, "fleet_bias.csv"),
    )
    fleet.to_csv(paths[0], index=False)
    biased.to_csv(paths[1], index=False)
    return paths


if __name__ == "__main__":
    print("\n".join(main(*sys.argv[1:2])))
