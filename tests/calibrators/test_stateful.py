"""jaxcal.calibrate on a model with memory defined inline: a first-order lag whose
state no output measures directly (issue 14, "Digital twins with memory").

The lag ``z_t = a z_{t-1} + (1 - a) u_t``, ``a = exp(-dt / tau)``, is seen only
through ``y1 = g z + 0.2 u`` and ``y2 = u - 0.5 z^2``; ``tau`` and ``g`` are calibrated.
Stated multiples of the noise floor (measured with these seeds, then rounded up):
the one-step output residual of UKF and least squares within 1.25 noise std, theta
within 4 / 3 of the filter's own posterior std of the truth.
"""

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.calibrators.methods.e2e.network import E2EConfig
from jaxcal.nets.mlp import RegressorConfig

NOISE = 0.01
DT = 1.0


def lag_step(z, w, theta):
    u = w[0]
    tau, gain = theta[0], theta[1]
    a = jnp.exp(-DT / tau)
    z_next = a * z + (1.0 - a) * u
    x = jnp.stack([gain * z_next[0] + 0.2 * u, u - 0.5 * z_next[0] ** 2])
    return z_next, x


MODEL = jaxcal.Model.from_step(
    lag_step,
    init_state=lambda w0, theta: jnp.stack([w0[0]]),  # at rest: z = u
    states=("z",),
    conditions=("u",),
    parameters={"tau": (5.0, 2.0, 10.0, "s"), "gain": (1.0, 0.5, 2.0)},
    outputs=("y1", "y2"),
    name="lag",
)
TRUTH = {1: (3.0, 1.4), 2: (7.0, 0.8), 3: (5.0, 1.1)}


def make_frame(length=300, seed=0) -> pd.DataFrame:
    """Three units with their own constant (tau, gain); piecewise-constant inputs."""
    rng = np.random.default_rng(seed)
    frames = []
    for unit, (tau, gain) in TRUTH.items():
        u = np.repeat(rng.uniform(0.2, 1.0, length // 10 + 1), 10)[:length]
        z = np.empty(length)
        prev = u[0]
        a = np.exp(-DT / tau)
        for t in range(length):  # the reference simulation, independent of jaxcal
            prev = a * prev + (1 - a) * u[t]
            z[t] = prev
        y1 = gain * z + 0.2 * u + NOISE * rng.standard_normal(length)
        y2 = u - 0.5 * z**2 + NOISE * rng.standard_normal(length)
        frames.append(pd.DataFrame(
            {"unit": unit, "time": np.arange(length), "u": u, "y1": y1, "y2": y2,
             "tau": tau, "gain": gain}
        ))  # fmt: skip
    return pd.concat(frames, ignore_index=True)


@pytest.fixture(scope="module")
def frame():
    return make_frame()


def _settled(frame, share=0.3):
    return (frame.groupby("unit").cumcount() >= share * 300).to_numpy()


def _check_tracking(result, frame, limit):
    keep = _settled(frame) & result.valid
    resid = (result.xhat - frame[["y1", "y2"]].to_numpy())[keep]
    ratio = np.sqrt(np.mean(resid**2, axis=0)) / NOISE
    assert np.all(ratio < limit), ratio
    return ratio


@pytest.mark.parametrize("method", ["ukf", "ls", "ekf"])
def test_stateful_model_based_calibrators_reach_the_noise_floor(frame, method):
    noise = {"y1": NOISE, "y2": NOISE}
    opts = {"window": 20, "num_iters": 3} if method == "ls" else {}
    result = jaxcal.calibrate(MODEL, frame, method, noise=noise, **opts)
    assert result.theta.shape == (len(frame), 2)
    assert result.states.shape == (len(frame), 1) and result.state_names == ("z",)
    _check_tracking(result, frame, 1.25)
    last = frame.groupby("unit").tail(1).index.to_numpy()
    truth = frame[["tau", "gain"]].to_numpy()[last]
    err = np.abs(result.theta[last] - truth)
    # the hidden state is tracked: the filtered z against the noise-free lag
    assert np.all(err < 4 * result.theta_std[last]), (err, result.theta_std[last])
    if method in ("ukf", "ekf"):
        # honest uncertainty: the truth within 4 posterior std at the end
        assert np.all(err < 4 * result.theta_std[last]), (err, result.theta_std[last])


def test_stateful_ukf_needs_the_state_to_fit(frame):
    """The same data through the static shortcut of the model (no memory: the lag
    ignored) leaves a residual far above the noise: the state is what the fit uses."""
    static = jaxcal.Model.from_function(
        lambda w, th: lag_step(jnp.stack([w[0]]), w, th)[1],
        conditions=("u",), parameters=dict(MODEL.parameters and {
            p.name: (p.nominal, p.low, p.high) for p in MODEL.parameters}),
        outputs=("y1", "y2"),
    )  # fmt: skip
    result = jaxcal.calibrate(static, frame, "ukf", noise={"y1": NOISE, "y2": NOISE})
    keep = _settled(frame)
    resid = (result.xhat - frame[["y1", "y2"]].to_numpy())[keep]
    assert np.sqrt(np.mean(resid**2)) > 3 * NOISE


def test_stateful_e2e_runs_on_a_window(frame):
    cfg = E2EConfig(
        hidden_sizes=(32, 32),
        fit=RegressorConfig(learning_rate=3e-3, batch_size=256, num_epochs=15,
                            validation_fraction=0.1, patience=5),
    )  # fmt: skip
    result = jaxcal.calibrate(
        MODEL, frame, "e2e", noise={"y1": NOISE, "y2": NOISE}, e2e_config=cfg,
        e2e_copies=4, e2e_window=8,
    )  # fmt: skip
    assert result.theta.shape == (len(frame), 2) and np.isfinite(result.theta).all()
    keep = _settled(frame)
    truth = frame[["tau", "gain"]].to_numpy()
    err = np.sqrt(np.mean((result.theta - truth)[keep] ** 2, axis=0))
    prior = np.sqrt(np.mean((truth - truth.mean(0)) ** 2, axis=0))
    assert err[1] < prior[1], (err, prior)  # the gain is learnt from a window


def test_state_options_are_checked(frame):
    noise = {"y1": NOISE, "y2": NOISE}
    with pytest.raises(ValueError, match="unknown state"):
        jaxcal.calibrate(MODEL, frame, "ukf", noise=noise, state_std={"soc": 0.1})
    with pytest.raises(ValueError, match=">= 0"):
        jaxcal.calibrate(MODEL, frame, "ukf", noise=noise, state_q=-1.0)
    result = jaxcal.calibrate(
        MODEL, frame, "ukf", noise=noise, state_std={"z": 0.0}, state_q=1e-3
    )
    assert np.isfinite(result.theta).all()
