"""The diagnosis of a model with memory, in output-error form (issues 14 and 24).

A thermal mass heated through a resistance: the wall temperature ``z`` is a hidden
state, the outputs are the outlet temperature and the heater load. Each unit is
simulated from its initial state with every candidate in the model, so no filter
stands between the model and the data: clean data give nothing (a filter's lag was
read as a sensor bias before), a bias on the load is found, and so is a bias on the
outlet, the output that pins the state (the one-step residual of a filter absorbed
it into the state estimate).
"""

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.data.readers import read_dataset
from jaxcal.diagnosis.pipeline import diagnose
from jaxcal.diagnosis.signatures import RowInputs, Tangent, signatures, zero_inputs
from jaxcal.diagnosis.synthetic import ar1_noise, rows_of

DT = 60.0  # s
AMBIENT = 290.0  # K


def wall_step(z, w, theta):
    """z = wall temperature (K); w = heater power (W); a fixed ambient."""
    power, ambient = w[0], AMBIENT
    resistance, capacity = theta[0], theta[1]  # K/W, J/K
    rate = DT / (resistance * capacity)
    a = jnp.exp(-rate)
    z_next = a * z + (1.0 - a) * (ambient + power * resistance)
    outlet = 0.7 * z_next[0] + 0.3 * ambient
    return z_next, jnp.stack([outlet, power * 1e-3 + 0.01 * (z_next[0] - ambient)])


MODEL = jaxcal.Model.from_step(
    wall_step,
    init_state=lambda w0, theta: jnp.stack([AMBIENT + w0[0] * theta[0]]),
    states={"wall": "K"},
    conditions={"power": "W"},
    parameters={"R": (0.05, 0.02, 0.1, "K/W"), "C": (2e4, 1e4, 4e4, "J/K")},
    outputs={"outlet": "K", "load": "kW"},
    name="wall",
)
NOISE = {"outlet": 0.05, "load": 0.002}


def _dataset(bias: float, outlet_bias: float = 0.0, phi: float = 0.0, seed=1):
    rng = np.random.default_rng(seed)
    frames = []
    for unit in range(3):
        n = 120
        power = np.repeat(rng.uniform(0, 3000, n // 12), 12)
        r_true = 0.05 + 0.01 * unit
        z, xs = jnp.array([AMBIENT + power[0] * r_true]), []
        for t in range(n):
            z, x = wall_step(z, jnp.array([power[t]]), jnp.array([r_true, 2e4]))
            xs.append(np.asarray(x))
        x = np.array(xs)
        noise = ar1_noise(rng, (n, 2), np.zeros(n, int), phi)
        x[:, 0] += NOISE["outlet"] * noise[:, 0] + outlet_bias
        x[:, 1] += NOISE["load"] * noise[:, 1] + bias
        frames.append(pd.DataFrame({
            "unit": unit, "time": np.arange(n), "power": power,
            "outlet": x[:, 0], "load": x[:, 1], "R": r_true,
        }))  # fmt: skip
    return read_dataset(pd.concat(frames, ignore_index=True), MODEL)


def test_signatures_through_the_states_match_finite_differences():
    """The output-error signatures: forward derivatives through the simulated state
    (a change of R at one row moves every later output)."""
    data = _dataset(0.0).select_units([0])
    rows = rows_of(data.w, data.unit, [0, 1])
    n = data.num_rows
    base = zero_inputs(MODEL, n, 1)
    profile = (np.arange(n) >= 30) * 0.005  # R steps up at row 30
    sig = signatures(MODEL, rows, base, [Tangent("parameter", 0, profile)])
    moved = base._replace(theta=base.theta + np.outer(profile, [1e-3, 0.0]))
    fd = (signatures(MODEL, rows, moved).y - sig.y) / 1e-3
    np.testing.assert_allclose(sig.cols[:, :, 0], fd, rtol=1e-4, atol=1e-7)
    assert np.all(sig.cols[:30, :, 0] == 0) and np.all(sig.cols[40:, 0, 0] != 0)
    assert isinstance(base, RowInputs)


def test_a_sensor_bias_is_found():
    result = diagnose(_dataset(bias=0.01), MODEL, ("R",), noise_std=NOISE)
    # a power-meter offset moves the load the same way: the two may share a
    # signature, then both are named
    assert result.verdict in ("identified", "confounded"), result.verdict
    found = result.identified[0]
    assert found["name"] == "sensor_bias[load]" and found["unit"] == "kW"
    assert abs(found["size"] - 0.01) < 4 * found["std"] + 0.001


def test_a_bias_on_the_output_that_pins_the_state_is_found():
    result = diagnose(_dataset(0.0, outlet_bias=0.3), MODEL, ("R",), noise_std=NOISE)
    assert result.added and result.added[0] == "sensor_bias[outlet]", result.added
    assert abs(result.identified[0]["size"] - 0.3) < 0.05


@pytest.mark.parametrize("phi", [0.0, 0.7])
def test_clean_data_give_no_effect(phi):
    """White or coloured noise, the noise levels estimated: nothing is found (a
    filter's lag, or the colour, read as a fault before)."""
    result = diagnose(_dataset(bias=0.0, phi=phi), MODEL, ("R",))
    assert result.verdict == "none" and result.added == [], result.added
