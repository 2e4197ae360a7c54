"""Where the model misfits the data, the std is flagged (``result.misfit``) and noted
(``jaxcal/calibrators/uncertainty/misfit_check.py``).

A tank whose level carries a slow departure the model lacks: the UKF's ``leak``
absorbs it, and its 90 % interval holds the truth on a few percent of the rows while
the innovations are strongly coloured; the same tank without the departure is left
unflagged, its coverage in the band.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.calibrators.uncertainty.misfit_check import (
    COLOURED,
    long_run_ratio,
    misfit_note,
    misfit_rows,
)

Z90 = 1.6448536269514722
NOISE = 0.02


def _ar1(rng, n, rho):
    out = np.zeros(n)
    shocks = rng.standard_normal(n)
    for t in range(1, n):
        out[t] = rho * out[t - 1] + shocks[t]
    return out


def test_the_ratio_is_one_for_white_noise_and_the_ar1_value_for_ar1():
    rng = np.random.default_rng(0)
    assert abs(long_run_ratio(rng.standard_normal(4000)) - 1.0) < 0.15
    # an AR(1) of 0.9: (1 + 0.9) / (1 - 0.9) = 19
    assert 19 * 0.75 < long_run_ratio(_ar1(rng, 4000, 0.9)) < 19 * 1.25


def test_only_the_coloured_unit_is_flagged_in_any_row_order():
    rng = np.random.default_rng(1)
    n = 400
    unit = np.repeat([1, 2, 3], n)
    time = np.tile(np.arange(n), 3)
    z = rng.standard_normal((3 * n, 2))
    z[unit == 2, 1] = _ar1(rng, n, 0.9)  # unit 2's second output: a misfit
    z[np.flatnonzero(unit == 1)[:10], 0] = np.nan  # missing outputs: left out
    used = np.ones(3 * n, bool)
    used[unit == 3] = time[unit == 3] < 20  # unit 3: too few rows to judge
    order = rng.permutation(3 * n)
    misfit, ratio = misfit_rows(unit[order], time[order], z[order], used[order])
    np.testing.assert_array_equal(misfit, unit[order] == 2)
    judged = unit[order] != 3
    assert np.all(np.isnan(ratio[~judged]))
    assert np.all(ratio[unit[order] == 2, 1] > COLOURED)
    assert np.all(ratio[judged & (unit[order] == 1)] < 1.5)
    (note,) = misfit_note(ratio, unit[order], ["flow", "level"])
    assert "of unit 2 are" in note and "level " in note and "flow" not in note
    assert misfit_note(np.ones((3, 2)), np.arange(3), ["flow", "level"]) == []
    none = misfit_rows(unit, time, z, np.zeros(3 * n, bool))  # no row used
    assert not none[0].any() and np.isnan(none[1]).all()


def _tank(w, theta):
    heat, inflow = w
    leak, loss = theta
    level = inflow / leak
    return jnp.stack(
        [level, 20 + heat / (inflow * (1 + loss)), leak * level * (1 - loss)]
    )


def _tank_data(misfit: float, seed: int = 0, units: int = 2, n: int = 300):
    """The README's tank, ``misfit`` x the noise of a slow wave on its level."""
    rng = np.random.default_rng(seed)
    frames = []
    for u in range(units):
        w = rng.uniform([5.0, 0.5], [30.0, 2.0], (n, 2))
        theta = np.tile([rng.uniform(0.8, 1.5), rng.uniform(0.05, 0.4)], (n, 1))
        x = np.array(jax.vmap(_tank)(w, theta))  # a writable copy
        x += NOISE * rng.standard_normal(x.shape)
        wave = np.sin(2 * np.pi * np.arange(n) / 60 + u)
        x[:, 0] += misfit * NOISE * wave * w[:, 1]  # a dynamics the model lacks
        frame = pd.DataFrame(
            np.hstack([w, x]), columns=["heat", "inflow", "level", "temp", "outflow"]
        )
        frame["unit"], frame["time"] = u + 1, np.arange(n)
        frame["leak"], frame["loss"] = theta[:, 0], theta[:, 1]
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


@pytest.mark.parametrize("noise", ["given", "estimated"])
def test_a_misfit_tank_is_flagged_and_a_fitting_one_is_not(noise, tmp_path):
    model = jaxcal.Model.from_function(
        _tank,
        conditions={"heat": "kW", "inflow": "kg/s"},
        parameters={"leak": (1.0, 0.5, 2.0, "1/s"), "loss": (0.1, 0.0, 0.5)},
        outputs={"level": "m", "temp": "degC", "outflow": "kg/s"},
        name="tank",
    )
    given = dict.fromkeys(model.output_names, NOISE) if noise == "given" else None

    def run(wave, **keep_std):
        data = _tank_data(wave)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            result = jaxcal.calibrate(
                model, data, "ukf", noise=given, progress=False, **keep_std
            )
        keep = result.valid & (data.time.to_numpy() >= 30)
        err = np.abs(result.theta - data[["leak", "loss"]].to_numpy())
        return result, (err <= Z90 * result.theta_std)[keep].mean(0)

    # asked to keep it, the std shows why it is withheld by default
    kept, covered = run(10.0, misfit="keep")
    assert covered[0] < 0.3  # leak absorbs the misfit: its std is far too small
    assert kept.misfit.all() and np.isfinite(kept.theta_std).all()
    misfit, _ = run(10.0)  # the default: withheld on every flagged row, and said
    assert misfit.misfit.all() and np.isnan(misfit.theta_std).all()
    np.testing.assert_array_equal(misfit.theta, kept.theta)
    expected = "the one-step innovations of units 1, 2 are autocorrelated"
    assert any(expected in n and "withheld" in n for n in misfit.notes)
    loaded = jaxcal.CalibrationResult.load(misfit.save(tmp_path / "r.parquet"))
    np.testing.assert_array_equal(loaded.misfit, misfit.misfit)
    assert np.isnan(loaded.theta_std).all()
    fitting, covered = run(0.0)
    assert not fitting.misfit.any()
    assert not any("autocorrelated" in n for n in fitting.notes)
    assert covered.min() >= 0.85  # the tank's own: 0.95-0.99
