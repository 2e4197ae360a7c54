"""jaxcal.calibrate on a small model defined in the tests (not a turbofan)."""

import jax.numpy as jnp
import numpy as np
import pytest
from support.tank import MODEL, NOISE, make_frame, tank

import jaxcal
from jaxcal.calibrators.methods.e2e.network import E2EConfig
from jaxcal.nets.mlp import RegressorConfig


@pytest.fixture(scope="module")
def frame():
    return make_frame()


def _late_rmse(result, frame):
    late = frame.time.to_numpy() >= 20
    truth = frame[list(result.theta_names)].to_numpy()
    return np.sqrt(np.mean((result.theta[late] - truth[late]) ** 2, axis=0))


@pytest.mark.parametrize("method", ["ukf", "ls", "ekf"])
def test_model_based_methods_track_the_parameters_in_row_order(frame, method):
    noise = dict(zip(MODEL.output_names, NOISE, strict=True))
    options = {"window": 8} if method == "ls" else {}  # a short window lags less
    result = jaxcal.calibrate(MODEL, frame, method=method, noise=noise, **options)
    assert result.theta.shape == (len(frame), 2)
    assert result.valid.all()
    rmse = _late_rmse(result, frame)
    assert rmse[0] < 0.05 and rmse[1] < 0.05, rmse
    if method in ("ukf", "ekf"):  # the filters' posterior std
        assert result.theta_std.shape == result.theta.shape
        assert np.all(result.theta_std > 0)


def test_noise_is_estimated_when_not_given(frame):
    result = jaxcal.calibrate(MODEL, frame, method="ukf")
    assert result.problem.noise_source.startswith("estimated")
    # within a factor of three of the truth (the window lags the drift a little)
    ratio = result.problem.noise_std / NOISE
    assert np.all((ratio > 1 / 3) & (ratio < 3)), ratio


def test_e2e_learns_the_inverse_from_simulations(frame):
    cfg = E2EConfig(
        hidden_sizes=(32, 32),
        fit=RegressorConfig(learning_rate=3e-3, batch_size=128, num_epochs=40,
                            validation_fraction=0.1, patience=10),
    )  # fmt: skip
    noise = dict(zip(MODEL.output_names, NOISE, strict=True))
    result = jaxcal.calibrate(
        MODEL, frame, method="e2e", noise=noise, theta=["leak"], e2e_config=cfg
    )
    assert _late_rmse(result, frame)[0] < 0.15


def test_bad_samples_are_skipped_and_flagged(frame):
    bad = frame.copy()
    bad.loc[5, "heat"] = 80.0  # outside the model's condition range
    noise = dict(zip(MODEL.output_names, NOISE, strict=True))
    result = jaxcal.calibrate(MODEL, bad, method="ukf", noise=noise)
    assert not result.valid[5] and result.reason[5] == "w_out_of_range"
    assert result.valid.sum() == len(frame) - 1
    assert result.num_flagged == {"w_out_of_range": 1}


def test_front_door_errors_are_clear(frame):
    with pytest.raises(ValueError, match="method must be one of"):
        jaxcal.calibrate(MODEL, frame, method="kalman")
    with pytest.raises(ValueError, match="unknown option"):
        jaxcal.calibrate(MODEL, frame, method="ukf", noise=None, windw=3)
    with pytest.raises(ValueError, match=r"misfit must be one of \('withhold', 'keep'"):
        jaxcal.calibrate(MODEL, frame, method="ukf", misfit="drop")
    with pytest.raises(ValueError, match="unknown name"):
        jaxcal.calibrate(MODEL, frame, theta=["leek"])
    with pytest.raises(ValueError, match="run="):
        jaxcal.calibrate(MODEL, frame, method="policy")


def test_condition_jitter_just_outside_the_range_is_clipped_and_noted(frame):
    jitter = frame.copy()
    jitter.loc[7, "heat"] = -0.2  # range [0, 50]: within 1 % of its width below 0
    # the readings of a true heat of 0 (else the row is, rightly, an outlier)
    row = jitter.loc[7]
    x = tank(jnp.array([0.0, row.inflow]), jnp.array([row.leak, row.loss]))
    jitter.loc[7, list(MODEL.output_names)] = np.asarray(x)
    noise = dict(zip(MODEL.output_names, NOISE, strict=True))
    result = jaxcal.calibrate(MODEL, jitter, method="ukf", noise=noise)
    assert result.valid.all()
    assert result.notes == ("heat just outside its range (jitter) set to 0 on 1 rows",)
