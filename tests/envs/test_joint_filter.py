"""The joint filter of a model with memory (jaxcal.envs.joint_filter) against a numpy
Kalman reference (the env and the deployed calibrator agree on it:
tests/training/test_train_stateful.py)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from jaxcal.envs.joint_filter import (
    conditioned_state,
    initial_joint_cov,
    joint_filter_feature,
    step_with_joint,
)


@struct.dataclass
class _Params:
    x_std: jnp.ndarray
    x_noise: jnp.ndarray
    theta_low: jnp.ndarray
    theta_high: jnp.ndarray
    step_ref: jnp.ndarray


def _linear_step(z, theta):
    # z' = 0.9 z + 0.5 theta_0 ; x = 2 z' + theta_1  (one state, two parameters)
    z_next = 0.9 * z + 0.5 * theta[:1]
    return z_next, 2.0 * z_next + theta[1:]


def test_joint_update_is_the_kalman_filter_of_state_and_theta():
    # one update from a correlated prior: the covariance and the state and theta
    # steps are the linear Kalman filter's on (z, u), u = theta / half, with theta's
    # random walk before the sample (numpy reference)
    low, high = jnp.array([-1.0, -2.0]), jnp.array([1.0, 2.0])
    half = np.array([1.0, 2.0])
    params = _Params(
        x_std=jnp.array([0.5]), x_noise=jnp.array([0.1]), theta_low=low,
        theta_high=high, step_ref=jnp.array([1.0, 1.0]),
    )  # fmt: skip
    z, theta, sens = jnp.array([0.3]), jnp.array([0.2, -0.4]), jnp.zeros((1, 2))
    jac, sens2, ah, z_next, xhat = step_with_joint(
        _linear_step, z, theta, sens, jnp.asarray(half)
    )
    a, h = (np.asarray(m) for m in ah)
    np.testing.assert_allclose(a, [[0.9, 0.5 * half[0], 0.0]], rtol=1e-6)
    np.testing.assert_allclose(h, [[1.8, 1.0 * half[0], 1.0 * half[1]]], rtol=1e-6)
    np.testing.assert_allclose(sens2, [[0.5, 0.0]], rtol=1e-6)
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.25, 0.02], [0.0, 0.02, 0.16]])
    x_obs, q = 1.1, 0.05
    resid = (x_obs - np.asarray(xhat)) / 0.5
    new_cov, feature, dz, du = joint_filter_feature(
        jnp.asarray(cov), jnp.asarray(resid), ah, params, 0.5, q
    )
    pred = cov + np.diag([0.0, q**2, q**2])
    m = np.array([[0.9, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    s = h @ pred @ h.T + 0.1**2
    gain = m @ pred @ h.T / s
    ref_cov = m @ pred @ m.T - gain @ gain.T * s
    step = gain[:, 0] * (x_obs - float(xhat[0]))
    np.testing.assert_allclose(new_cov, ref_cov, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(np.concatenate([dz, du]), step, rtol=1e-5)
    assert feature.shape == (2,) and np.all(np.isfinite(feature))
    # the policy taking the filter's step leaves the corrected state; another step
    # moves it by the posterior regression on theta
    z_post = np.asarray(z_next) + np.asarray(dz)
    same = conditioned_state(jnp.asarray(z_post), new_cov, du, du)
    np.testing.assert_allclose(same, z_post, rtol=1e-6)
    other = du + jnp.array([0.1, 0.0])
    moved = conditioned_state(jnp.asarray(z_post), new_cov, other, du)
    regress = ref_cov[:1, 1:] @ np.linalg.inv(ref_cov[1:, 1:])
    np.testing.assert_allclose(moved, z_post + regress @ [0.1, 0.0], rtol=1e-5)
    prior = initial_joint_cov(1, 2, jnp.float32, 0.5)
    np.testing.assert_allclose(prior, np.diag([0.0, 0.25, 0.25]))


def test_joint_prior_carries_the_first_states_dependence_on_theta():
    # the first state z0 = 3 theta_0 - theta_1 (w ignored): with theta's prior
    # C_uu in half-box units u = theta / h, the state's variance is S C_uu S^T and
    # its cross term S C_uu, S = dz0 / du = [3 h_0, -h_1]; dynamics that cannot say
    # (no init_at) keep the covariance they were given
    from jaxcal.envs.joint_filter import joint_prior
    from jaxcal.envs.memory import StatefulDynamics

    def init_at(dyn_params, w0, theta):
        return jnp.stack([3.0 * theta[0] - theta[1]])

    dyn = StatefulDynamics(None, None, 1, init_at)
    half = jnp.array([0.5, 2.0])
    cov = initial_joint_cov(1, 2, jnp.float32, 0.7)
    got = np.asarray(joint_prior(dyn, None, jnp.zeros(1), jnp.zeros(2), cov, half))
    s = np.array([[1.5, -2.0]])
    c_uu = 0.49 * np.eye(2)
    np.testing.assert_allclose(got[:1, :1], s @ c_uu @ s.T, rtol=1e-6)
    np.testing.assert_allclose(got[:1, 1:], s @ c_uu, rtol=1e-6)
    np.testing.assert_allclose(got[1:, 1:], c_uu, rtol=1e-6)
    unknown = StatefulDynamics(None, None, 1)
    np.testing.assert_array_equal(
        joint_prior(unknown, None, jnp.zeros(1), jnp.zeros(2), cov, half), cov
    )


@pytest.mark.parametrize(
    "rows, inner, cols", [(2, 4, 4), (4, 4, 2), (4, 3, 4), (3, 5, 4)]
)
def test_written_out_product_is_the_dot(rows, inner, cols):
    # the joint filter's small products written out (_product) are the dot to
    # float32's rounding, one matrix and batched over units (vmap: a fleet), with
    # zeros and an operand transposed; a longer contraction is the dot itself
    from jaxcal.envs.joint_filter import _product

    rng = np.random.default_rng(rows * 100 + inner * 10 + cols)
    a = rng.normal(size=(64, rows, inner)).astype(np.float32)
    b = rng.normal(size=(64, inner, cols)).astype(np.float32)
    a[:16][rng.random((16, rows, inner)) < 0.4] = 0.0
    want = np.einsum("uik,ukj->uij", a.astype(np.float64), b.astype(np.float64))
    got = jax.jit(jax.vmap(_product))(a, b)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(_product(a[0], b[0]), want[0], rtol=1e-5, atol=1e-6)
    bt = np.ascontiguousarray(np.swapaxes(b, 1, 2))
    got_t = jax.jit(jax.vmap(lambda x, y: _product(x, y.T)))(a, bt)
    np.testing.assert_allclose(got_t, want, rtol=1e-5, atol=1e-6)
