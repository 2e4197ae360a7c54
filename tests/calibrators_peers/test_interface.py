"""The calibrator interface: scan/mask semantics, fleets, keys, measure_declared."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from jaxcal.calibrators.interface import (
    Calibrator,
    CalStepOutput,
    Measurement,
    check_measurement,
    run_calibrator,
    run_fleet,
)
from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES
from jaxcal.paper.methods import measure_declared  # the turbofan's, for the paper

NUM_STEPS, NUM_SENSORS, NUM_CONDITIONS = 7, 3, 2


def make_e2e_like() -> Calibrator:
    """theta_t = G(w_t, x_t, x_{t-1}): the state is the previous measurement."""

    def init(key, w0, x0):
        del key, w0
        return x0

    def step(x_prev, w_t, x_t):
        theta = jnp.stack([jnp.sum(x_t - x_prev), w_t[0] * x_t[0]])
        return x_t, CalStepOutput(theta=theta, xhat=x_t, aux=None)

    return Calibrator(init, step)


@struct.dataclass
class PolicyState:
    xhat: jax.Array  # [S]
    key: jax.Array


def make_rl_like() -> Calibrator:
    """RL-like: theta_t = pi(xhat_{t-1}, x_t, w_t) + noise; xhat_t = D(., theta_t)."""

    def init(key, w0, x0):
        del w0
        return PolicyState(xhat=x0, key=key)

    def step(state, w_t, x_t):
        key, key_act = jax.random.split(state.key)
        theta = 0.5 * (x_t - state.xhat)[:2] + 0.1 * jax.random.normal(key_act, (2,))
        xhat = state.xhat + jnp.sum(theta) + 0.01 * w_t[1]
        aux = {"gap": jnp.sum((x_t - xhat) ** 2)}
        return PolicyState(xhat, key), CalStepOutput(theta=theta, xhat=xhat, aux=aux)

    return Calibrator(init, step)


def _data(seed=0, num_units=None):
    rng = np.random.default_rng(seed)
    lead = () if num_units is None else (num_units,)
    w = jnp.asarray(rng.normal(size=(*lead, NUM_STEPS, NUM_CONDITIONS)))
    x = jnp.asarray(rng.normal(size=(*lead, NUM_STEPS, NUM_SENSORS)))
    return w, x


def _python_loop(cal, w, x, key=None):
    state = cal.init(key, w[0], x[0])
    outs = []
    for t in range(w.shape[0]):
        state, out = cal.step(state, w[t], x[t])
        outs.append(out)
    return jax.tree.map(lambda *a: jnp.stack(a), *outs)


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_run_calibrator_equals_python_loop(use_jit):
    w, x = _data()
    cal = make_e2e_like()
    run = jax.jit(run_calibrator, static_argnums=0) if use_jit else run_calibrator
    out = run(cal, w, x)
    ref = _python_loop(cal, w, x)
    np.testing.assert_allclose(out.theta, ref.theta, atol=1e-12)
    np.testing.assert_allclose(out.xhat, ref.xhat, atol=1e-12)
    assert out.aux is None
    # The first step sees x_prev = x_0 from init.
    assert float(out.theta[0, 0]) == 0.0


def test_masked_rows_keep_state_and_repeat_outputs():
    w, x = _data(1)
    cal = make_rl_like()
    key = jax.random.key(0)
    mask = jnp.array([False, False, True, True, False, True, True])
    out = run_calibrator(cal, w, x, mask, key=key)
    valid = np.flatnonzero(np.asarray(mask))
    # init gets the first valid row, as run_calibrator promises.
    ref = _python_loop(cal, w[valid], x[valid], key=key)
    np.testing.assert_allclose(out.theta[valid], ref.theta, atol=1e-12)
    np.testing.assert_allclose(out.aux["gap"][valid], ref.aux["gap"], atol=1e-12)
    # Leading padding outputs zeros; a gap repeats the last valid output.
    np.testing.assert_array_equal(out.theta[:2], 0.0)
    np.testing.assert_array_equal(out.theta[4], out.theta[3])
    np.testing.assert_array_equal(out.xhat[4], out.xhat[3])


def test_run_fleet_equals_per_unit_runs_and_uses_each_key():
    num_units = 3
    w, x = _data(2, num_units)
    mask = jnp.arange(NUM_STEPS)[None, :] < jnp.array([[7], [5], [3]])
    keys = jax.random.split(jax.random.key(1), num_units)
    cal = make_rl_like()
    run = jax.jit(run_fleet, static_argnums=0)
    out = run(cal, w, x, mask, keys=keys)
    chex.assert_shape(out.theta, (num_units, NUM_STEPS, 2))
    chex.assert_shape(out.aux["gap"], (num_units, NUM_STEPS))
    run_one = jax.jit(run_calibrator, static_argnums=0)
    for u in range(num_units):
        ref = run_one(cal, w[u], x[u], mask[u], key=keys[u])
        chex.assert_trees_all_close(
            jax.tree.map(lambda a, u=u: a[u], out), ref, atol=1e-12
        )
    # Identical data, different keys: the stochastic steps must differ.
    out_same = run(
        cal,
        jnp.stack([w[0]] * num_units),
        jnp.stack([x[0]] * num_units),
        mask,
        keys=keys,
    )
    assert not np.allclose(out_same.theta[0], out_same.theta[1])  # keys differ


def test_measure_declared_holds_undeclared_parameters_and_selects_sensors():
    def measure_full(w, theta_full):
        return jnp.concatenate([theta_full * w[0], jnp.array([jnp.sum(theta_full**2)])])

    theta_base = jnp.linspace(-0.05, 0.0, 10)
    declared = ["HPT_eff_mod", "LPC_flow_mod"]
    measure = measure_declared(
        measure_full, theta_base, declared, sensor_idx=[6, 3, 10]
    )
    theta = jnp.array([0.3, -0.2])
    positions = jnp.array([HEALTH_NAMES.index(n) for n in declared])  # [6, 3]
    full = theta_base.at[positions].set(theta)
    w = jnp.array([2.0, 1.0])
    np.testing.assert_allclose(
        measure(w, theta), measure_full(w, full)[jnp.array([6, 3, 10])]
    )
    jac = jax.jacfwd(measure, argnums=1)(w, theta)
    chex.assert_shape(jac, (3, 2))
    np.testing.assert_allclose(jac[:2], 2.0 * jnp.eye(2))  # sensors 6, 3 = declared


@pytest.mark.parametrize(
    "declared,match",
    [
        ([], "at least one"),
        ([1, 1], "unique"),
        ([10], ">= number"),
        (["bogus"], "unknown"),
    ],
)
def test_measure_declared_rejects_bad_indices(declared, match):
    with pytest.raises(ValueError, match=match):
        measure_declared(lambda w, th: th, jnp.zeros(10), declared)


def test_bad_shapes_raise_clear_errors():
    cal = make_e2e_like()
    w, x = _data()
    with pytest.raises(ValueError, match="equal T"):
        run_calibrator(cal, w, x[:-1])
    with pytest.raises(ValueError, match="mask"):
        run_calibrator(cal, w, x, jnp.ones(3, bool))
    with pytest.raises(ValueError, match=r"\[U, T, Wd\]"):
        run_fleet(cal, w, x)
    with pytest.raises(ValueError, match="noise_std > 0"):
        check_measurement(
            Measurement(centre=jnp.zeros(2), noise_std=jnp.array([1.0, -1.0]))
        )
    with pytest.raises(ValueError, match=r"\.centre and \.noise_std"):
        check_measurement(object())
