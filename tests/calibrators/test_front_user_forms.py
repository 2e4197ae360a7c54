"""The forms a new user writes (issue 42): one noise number for every output, and a
state observed directly as an output under the state's own name."""

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal

DT = 60.0  # s per sample


def _room(z, w, theta):
    """One air mass: ``T_air`` relaxes to the outside with time constant ``tau`` and
    is warmed by the heater; the output is the state itself."""
    tau, gain = theta
    t_air = z[0] + DT / tau * (w[0] - z[0]) + gain * w[1]
    return jnp.stack([t_air]), jnp.stack([t_air])


def _model(outputs=("T_air",)):
    return jaxcal.Model.from_step(
        _room,
        init_state=lambda w0, theta: w0[:1],
        states=(("T_air", "degC"),),
        conditions=("T_out", "heat"),
        parameters={"tau": (1800.0, 600.0, 6000.0, "s"), "gain": (0.5, 0.1, 2.0)},
        outputs=outputs,
    )


def _data(theta=(1200.0, 0.8), n=120, seed=0):
    rng = np.random.default_rng(seed)
    w = np.stack([np.full(n, 5.0), np.repeat(rng.uniform(0.0, 1.0, n // 10), 10)], 1)
    _, x = jax.lax.scan(
        lambda z, wi: _room(z, wi, jnp.asarray(theta)), jnp.asarray(w[0, :1]), w
    )
    x = np.asarray(x)[:, 0] + 0.02 * rng.standard_normal(n)
    return pd.DataFrame({"T_out": w[:, 0], "heat": w[:, 1], "T_air": x})


def test_an_output_may_be_the_state_of_the_same_name():
    model = _model(outputs=(("T_air", "degC"),))
    assert model.output_names == model.state_names == ("T_air",)
    with pytest.raises(ValueError, match="'T_air' is both a condition and an output"):
        jaxcal.Model.from_function(
            lambda w, th: w, conditions=("T_air",), parameters={"a": (1, 0, 2)},
            outputs=("T_air",),
        )  # fmt: skip
    with pytest.raises(ValueError, match="an output that is a state has its unit"):
        _model(outputs=(("T_air", "K"),))


def test_state_named_output_calibrates_end_to_end_with_one_noise_number(tmp_path):
    result = jaxcal.calibrate(
        _model(), _data(), method="ukf", noise=0.02, progress=False, q=1e-6
    )
    np.testing.assert_array_equal(result.problem.noise_std, [0.02])
    # the noise to pass on (docs/fleet.md), kept by a result loaded without its model
    assert result.noise == {"T_air": 0.02}
    assert jaxcal.CalibrationResult.load(result.save(tmp_path / "r.parquet")).noise == {
        "T_air": 0.02
    }
    frame = result.to_frame()
    assert {"T_air", "T_air_hat", "tau", "gain"} <= set(frame.columns)
    last = frame.iloc[-1]
    assert abs(last["gain"] - 0.8) < 0.02 and abs(last["tau"] - 1200.0) < 30.0
    # the filtered state tracks the measured output it is
    assert np.abs(frame["T_air"] - _data()["T_air"]).median() < 0.1


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), float("inf")])
def test_one_noise_number_must_be_a_finite_std(bad):
    with pytest.raises(ValueError, match=r"noise=.*expected a finite std > 0"):
        jaxcal.calibrate(_model(), _data(n=20), method="ls", noise=bad, progress=False)
