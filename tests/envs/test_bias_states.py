"""The filter's output-bias states (``tune.bias``, :mod:`jaxcal.envs.bias_states`).

At a walk that changes nothing the filter with bias states is the filter without
them (the tuning starts there), on a static model (the filter on theta alone, with
its adaptive noise) and on one with memory (the joint filter); at a walk that lets a
bias grow, a sensor's step no longer pulls theta with it.
"""

import jax.numpy as jnp
import numpy as np
from support.norm import own_norm

from jaxcal.calibrators.interface import run_fleet
from jaxcal.calibrators.methods.policy.calibrator import (
    make_policy_calibrator,
    policy_params_from_env,
    with_output_states,
)
from jaxcal.envs.bias_states import START_WALK, with_bias_block
from jaxcal.envs.increment import increment_step_ref
from jaxcal.envs.memory import StatefulDynamics, as_stateful
from jaxcal.envs.tracking import make_env_params

U, T, S, W, P = 2, 240, 6, 2, 2
RNG = np.random.default_rng(5)
A = RNG.normal(size=(S, P))
B = RNG.normal(size=(S, W))
NOISE = 0.05
TRUTH = np.array([0.3, -0.6])


def linear(dyn_params, w_next, xhat, theta):
    del dyn_params, xhat
    return jnp.asarray(A) @ theta + jnp.asarray(B) @ w_next


def _lagged_step(dyn_params, z, w, xhat, theta):
    """A first-order lag on theta_0 (the state) beside a static output of theta_1."""
    del dyn_params, xhat
    z_next = 0.7 * z + 0.3 * (theta[:1] + w[:1])
    x = jnp.stack([z_next[0], theta[1] + w[1], z_next[0] - theta[1], theta[1] * w[0]])
    return z_next, x


LAGGED = StatefulDynamics(
    _lagged_step,
    lambda dp, w0: jnp.zeros(1, w0.dtype),
    1,
    lambda dp, w0, th: jnp.zeros(1, w0.dtype),
)


class StepActor:
    """Gain 1 on the filter's step (the observation's last entries before the age)."""

    def apply(self, _, obs):
        return jnp.arctanh(jnp.clip(obs[-P - 1 : -1], -0.999, 0.999)), None


def _fleet(dynamics, outputs, bias):
    w = RNG.normal(size=(U, T, W))
    dyn = as_stateful(dynamics)
    z = jnp.zeros((U, dyn.num_states)) if dyn.num_states else None
    rows = []
    for t in range(T):  # a test's data, host side
        if dyn.num_states:
            z, xt = jax_vmap_step(dyn, z, w[:, t])
        else:
            xt = np.stack(
                [np.asarray(dynamics(None, w[u, t], None, TRUTH)) for u in range(U)]
            )
        rows.append(np.asarray(xt))
    x = np.stack(rows, axis=1) + NOISE * RNG.normal(size=(U, T, outputs))
    x[:, T // 3 :, 0] += bias
    lengths = np.array([T, T])
    params = make_env_params(
        w, x, lengths, -np.ones(P), np.ones(P), None, stats=own_norm(w, x, lengths)
    )
    step_ref = (
        increment_step_ref(dyn, params, np.zeros(P), 1.0)
        if not dyn.num_states
        else np.full(P, 1e-3)  # the gate's scale: the feature divides it out
    )
    return (
        params.replace(
            step_ref=jnp.asarray(step_ref), x_noise=jnp.full(outputs, NOISE)
        ),
        w,
        x,
    )


def jax_vmap_step(dyn, z, w_t):
    import jax

    def one(zu, wu):
        return dyn.step(None, zu, wu, None, jnp.asarray(TRUTH))

    return jax.vmap(one)(z, jnp.asarray(w_t))


def _run(dynamics, params, w, x, walk, adapt=0):
    pp = policy_params_from_env(
        params, None, max_increment=1.0, gn_filter=True, filter_whole=True,
        filter_adapt=adapt,
    )  # fmt: skip
    if walk is not None:
        pp = with_output_states(pp, jnp.full(x.shape[-1], walk))
    cal = make_policy_calibrator(StepActor(), dynamics, pp)
    out = run_fleet(cal, jnp.asarray(w), jnp.asarray(x), jnp.ones((U, T), bool))
    return np.asarray(out.theta)


def test_bias_block_keeps_the_state_and_theta_blocks():
    cov = jnp.asarray([[1.0, 0.2, 0.1], [0.2, 2.0, 0.3], [0.1, 0.3, 3.0]])
    out = np.asarray(with_bias_block(cov, 1, 2))
    keep = [0, 3, 4]
    np.testing.assert_array_equal(out[np.ix_(keep, keep)], cov)
    assert not out[1:3].any() and not out[:, 1:3].any()


def test_a_walk_that_changes_nothing_is_the_filter_without_bias_states():
    params, w, x = _fleet(linear, S, bias=0.0)
    for adapt in (0, 16):  # the filter on theta alone, declared and adaptive noise
        plain = _run(linear, params, w, x, None, adapt)
        quiet = _run(linear, params, w, x, 0.0, adapt)
        np.testing.assert_allclose(quiet, plain, atol=2e-5)
        started = _run(linear, params, w, x, START_WALK, adapt)
        np.testing.assert_allclose(started, plain, atol=2e-3)
    params, w, x = _fleet(LAGGED, 4, bias=0.0)
    plain = _run(LAGGED, params, w, x, None)
    quiet = _run(LAGGED, params, w, x, 0.0)
    np.testing.assert_allclose(quiet, plain, atol=2e-5)  # the joint filter's too


def test_bias_states_keep_a_sensor_step_out_of_theta_on_a_model_with_memory():
    """The lag tells a sensor's offset from theta_0, whose effect moves through the
    state: the step pulls theta far less (measured 0.035 against 0.094 at this
    walk; on a static model the adaptive noise does this job, and a bias on every
    output cannot be told from theta)."""
    late = slice(T // 2, T)  # after the step, settled
    params, w, x = _fleet(LAGGED, 4, bias=4 * NOISE)
    plain = _run(LAGGED, params, w, x, None)
    biased = _run(LAGGED, params, w, x, 1e-1)
    err_plain = np.sqrt(np.mean((plain[:, late] - TRUTH) ** 2))
    err_biased = np.sqrt(np.mean((biased[:, late] - TRUTH) ** 2))
    assert err_biased < 0.5 * err_plain, (err_biased, err_plain)
