"""The diagnosis on a model that is not a turbofan: a pump defined here, in the test.

Its data go through a CSV and ``python -m jaxcal.diagnose model=<this file>:PUMP``
(in-process): an injected bias on one output is found and named in the model's units,
and the clean data give no effect.
"""

import json

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.cli.diagnose import main


def pump(w, theta):
    """``x [3] = (head m, power kW, t_out K)`` of a centrifugal pump."""
    flow, speed, t_in = w[0], w[1], w[2]
    wear, leak, friction = theta[0], theta[1], theta[2]
    viscous = 1.0 - 0.01 * (t_in - 300.0)  # warmer water, thinner, a little less head
    head = (60.0 * speed**2 * (1.0 - wear) - 10.0 * flow**2) * viscous
    eta = 0.8 * (1.0 - leak)
    power = 9.81 * flow * head / eta + 100.0 * friction * speed**3
    t_out = t_in + 0.05 * power * (1.0 - eta) / flow
    return jnp.stack([head, power, t_out])


PUMP = jaxcal.Model.from_function(
    pump,
    conditions={"flow": "m3/s", "speed": "-", "t_in": "K"},
    parameters={
        "wear": (0.0, 0.0, 0.3, "-"),
        "leak": (0.0, 0.0, 0.3, "-"),
        "friction": (0.0, 0.0, 1.0, "-"),
    },
    outputs={"head": "m", "power": "kW", "t_out": "K"},
    name="pump",
    condition_range=([0.3, 0.7, 270.0], [2.5, 1.3, 340.0]),
)
NOISE = np.array([0.1, 1.0, 0.05])  # head m, power kW, t_out K


def _write_csv(path, t_out_bias, units=4, steps=50):
    """``units`` units x ``steps`` time steps (default 4 x 50) at six duty points,
    wear drifting 0 -> 0.1, noise and an optional bias on t_out."""
    rng = np.random.default_rng(0)
    n = units * steps
    # six duty points (a plant runs at a few set points), each with a little jitter
    points = np.stack(
        [rng.uniform(0.6, 2.0, 6), rng.uniform(0.8, 1.2, 6), rng.uniform(285, 315, 6)],
        axis=1,
    )
    w = points[rng.integers(0, 6, n)] * (1.0 + 0.002 * rng.normal(size=(n, 3)))
    time = np.tile(np.arange(1, steps + 1), units)
    theta = np.zeros((n, 3))
    theta[:, 0] = 0.1 * time / steps
    x = np.stack([np.asarray(pump(wi, ti)) for wi, ti in zip(w, theta, strict=True)])
    x = x + NOISE * rng.normal(size=x.shape)
    x[:, 2] += t_out_bias
    frame = pd.DataFrame(
        {"flow": w[:, 0], "speed": w[:, 1], "t_in": w[:, 2], "head": x[:, 0],
         "power": x[:, 1], "t_out": x[:, 2], "unit": np.repeat(np.arange(units), steps),
         "time": time, "wear": theta[:, 0]}
    )  # fmt: skip
    frame.to_csv(path, index=False)
    return path


def _diagnose(tmp_path, bias):
    data = _write_csv(tmp_path / "pump.csv", bias)
    out = tmp_path / "out"
    argv = [f"model={__file__}:PUMP", f"data={data}", "calibrate=wear", f"out={out}"]
    assert main(argv) == 0
    rep = json.loads((out / "report.json").read_text())
    return rep, (out / "report.md").read_text()


def test_the_library_is_built_from_the_model():
    from jaxcal.diagnosis.kinds.table import build_library

    lib = build_library(PUMP, ("wear",), ("head", "t_out"), np.ones(2), np.ones(2))
    names = {c.name: c.unit for c in lib}
    assert "parameter[leak]" in names and "parameter[wear]" not in names
    assert names["condition_offset[t_in]"] == "K"
    assert names["sensor_bias[t_out]"] == "K" and names["sensor_gain[head]"] == "-"
    assert names["sensor_drift[head]"] == "m per 100 cycles"


def test_cli_finds_an_output_bias_and_names_it_in_the_model_units(tmp_path, capsys):
    rep, md = _diagnose(tmp_path, bias=0.5)
    assert rep["model"] == "pump" and rep["declared"] == ["wear"]
    assert rep["verdict"] == "identified", rep["ranking"][:3]
    found = rep["identified"][0]
    assert found["name"] == "sensor_bias[t_out]" and found["unit"] == "K"
    assert found["size"] == pytest.approx(0.5, abs=4 * found["std"] + 0.02)
    assert "| sensor_bias[t_out] |" in md and "| K |" in md
    assert rep["data"]["units_of"]["t_out"] == "K"
    assert (
        rep["after"]["tracking_rmse"]["t_out"]
        < 0.5 * rep["before"]["tracking_rmse"]["t_out"]
    )
    assert set(rep["before"]["theta_rmse"]) == {"wear"}
    assert "verdict: identified (sensor_bias[t_out]" in capsys.readouterr().out
    # the loop closed: the extended model, a file model= accepts, tracks the bias
    assert rep["extended_model"] == {
        "parameters": ["wear", "t_out_offset"],
        "file": "extended_model.json",
    }
    ext = jaxcal.models.load(str(tmp_path / "out" / "extended_model.json"))
    assert ext.parameter_names == ("wear", "t_out_offset")
    assert ext.output_names == PUMP.output_names
    x0 = np.asarray(pump(jnp.array([1.0, 1.0, 300.0]), jnp.array([0.05, 0, 0])))
    x1, _ = ext.evaluate(jnp.array([1.0, 1.0, 300.0]), jnp.array([0.05, 0.5]))
    np.testing.assert_allclose(np.asarray(x1) - x0, [0.0, 0.0, 0.5], atol=1e-9)


def test_cli_on_clean_data_reports_no_effect(tmp_path):
    rep, _ = _diagnose(tmp_path, bias=0.0)
    assert rep["verdict"] == "none" and rep["identified"] == [] and rep["added"] == []


def test_cli_names_a_bad_parameter_and_exits_2(tmp_path, capsys):
    data = _write_csv(tmp_path / "pump.csv", 0.0)
    argv = [f"model={__file__}:PUMP", f"data={data}", "calibrate=erosion"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "erosion" in err and "wear" in err
