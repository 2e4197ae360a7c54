"""The battery example's ECM (examples/battery/model.py) against closed forms, and
a joint-UKF recovery of R0 and Q on data the ECM itself generates (no pybamm)."""

from __future__ import annotations

import importlib.util
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _load_ecm():
    path = os.path.join(ROOT, "examples", "battery", "model.py")
    spec = importlib.util.spec_from_file_location("battery_ecm_model", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


ecm = _load_ecm()
THETA = np.array([0.03, 0.02, 60.0, 4.5])  # R0 [Ohm], R1 [Ohm], tau1 [s], Q [Ah]


def _simulate(current, dt, theta, z0=(0.9, 0.0)):
    """``(states [T, 2], voltage [T])`` of the ECM under ``current [T]``, ``dt [T]``."""

    def body(z, w):
        z, x = ecm.step(z, w, theta)
        return z, (z, x[0])

    w = jnp.stack([jnp.asarray(current), jnp.asarray(dt)], axis=1)
    return jax.lax.scan(body, jnp.asarray(z0), w)[1]


@pytest.mark.parametrize("transform", [lambda f: f, jax.jit])
def test_coulomb_counting_and_rc_response_match_closed_forms(transform):
    amps, n, dt = 5.0, 30, 10.0
    states, volts = transform(_simulate)(np.full(n, amps), np.full(n, dt), THETA)
    t = dt * np.arange(1, n + 1)
    soc = 0.9 - amps * t / (3600.0 * THETA[3])
    v_rc = THETA[1] * amps * (1.0 - np.exp(-t / THETA[2]))  # step response of an RC
    np.testing.assert_allclose(states[:, 0], soc, rtol=0, atol=1e-12)
    np.testing.assert_allclose(states[:, 1], v_rc, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(
        volts, ecm.ocv(jnp.asarray(soc)) - THETA[0] * amps - v_rc, atol=1e-12
    )


def test_irregular_sampling_gives_the_same_state_as_regular():
    # exact discretisation: 10 steps of 3 s + 1 of 30 s == 20 steps of 3 s
    regular, _ = _simulate(np.full(20, 4.0), np.full(20, 3.0), THETA)
    gappy, _ = _simulate(np.full(11, 4.0), np.r_[np.full(10, 3.0), 30.0], THETA)
    np.testing.assert_allclose(gappy[-1], regular[-1], rtol=1e-12)


def test_ocv_hits_its_knots_is_c1_and_increasing():
    knots = np.linspace(0.0, 1.0, ecm.OCV_VALUES.shape[0])
    np.testing.assert_allclose(ecm.ocv(jnp.asarray(knots)), ecm.OCV_VALUES, atol=1e-12)
    grad = jax.vmap(jax.grad(ecm.ocv))
    eps = 1e-9
    for k in knots[1:-1]:  # slope continuous across each knot, equal to the table
        left, right = grad(jnp.array([k - eps, k + eps]))
        assert abs(left - right) < 1e-5 * max(1.0, abs(left))
    fine = jnp.linspace(0.0, 1.0, 2001)
    assert bool(jnp.all(jnp.diff(ecm.ocv(fine)) > 0))
    # linear beyond the ends keeps the curve invertible for a filter's sigma points
    assert float(ecm.ocv(jnp.asarray(1.05))) > 4.2
    assert float(ecm.ocv(jnp.asarray(-0.05))) < 2.5


def test_model_from_step_builds_and_steps():
    model = ecm.MODEL
    assert model.is_stateful and model.state_names == ("soc", "v_rc1")
    assert model.condition_names == ("current", "dt")
    assert model.parameter_names == ("R0", "R1", "tau1", "Q")
    assert model.unit_of("Q") == "Ah"
    z0 = model.init_state(jnp.array([1.0, 10.0]), jnp.asarray(model.nominal))
    z1, x, info = model.step(z0, jnp.array([1.0, 10.0]), jnp.asarray(model.nominal))
    assert z1.shape == (2,) and x.shape == (1,) and bool(info.valid)
    _, _, bad = model.step(z0, jnp.array([100.0, 10.0]), jnp.asarray(model.nominal))
    assert not bool(bad.valid)  # 100 A is outside the condition range


def _synthetic_frame(theta, num_units=2, steps=1500, seed=0):
    """Pulsed discharge/charge streams from the ECM itself, 2 mV noise."""
    import pandas as pd

    rng = np.random.default_rng(seed)
    frames = []
    for unit in range(1, num_units + 1):
        levels, weights = [0.0, 5.0, 10.0, -5.0], [0.2, 0.35, 0.2, 0.25]
        pulses = rng.choice(levels, size=steps // 15, p=weights)
        current = np.repeat(pulses, 15)[:steps]
        current -= current.mean() * (np.arange(steps) >= steps // 2) * 2  # charge back
        dt = np.full(steps, 10.0)
        _, volts = _simulate(current, dt, theta)
        frames.append(pd.DataFrame({
            "unit": unit, "time": np.cumsum(dt), "current": current, "dt": dt,
            "voltage": np.asarray(volts) + 0.002 * rng.standard_normal(steps),
        }))  # fmt: skip
    return pd.concat(frames, ignore_index=True)


def test_joint_ukf_recovers_r0_and_capacity():
    import jaxcal

    truth = np.array([0.04, ecm.R1_FRESH, ecm.TAU1_FRESH, 4.5])
    frame = _synthetic_frame(truth)
    res = jaxcal.calibrate(
        ecm.MODEL, frame, method="ukf", theta=("R0", "Q"),
        noise={"voltage": 0.002}, q=1e-5, prior_std=0.25,
        state_std={"soc": 0.02, "v_rc1": 0.01},
        state_q={"soc": 1e-5, "v_rc1": 1e-4},
    )  # fmt: skip
    last = res.theta[frame.groupby("unit").tail(1).index]
    # tolerances: 1 mOhm on R0 (2.5 %), 0.05 Ah on Q (1.1 %) after 4 h of pulses
    np.testing.assert_allclose(last[:, 0], 0.04, atol=1e-3)
    np.testing.assert_allclose(last[:, 1], 4.5, atol=0.05)
