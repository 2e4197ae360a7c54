"""Incremental actions: the gate, the environment in increment mode, and the deployed
calibrator against the environment, on a linear model whose Gauss-Newton step is known.

The closed loop with the ideal feedback (a Gauss-Newton step through the gate) must
drive theta to the truth on noise-free data to rounding: the formulation itself has no
resolution floor, whatever the network later learns.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.norm import own_norm

from jaxcal.calibrators.interface import run_fleet
from jaxcal.calibrators.methods.policy.calibrator import (
    IncrementPolicyParams,
    make_policy_calibrator,
    policy_params_from_env,
)
from jaxcal.envs.increment import (
    apply_increment,
    increment_observation,
    increment_step_ref,
    sensitivity,
)
from jaxcal.envs.memory import as_stateful
from jaxcal.envs.tracking import EnvConfig, make_env_params, make_tracking_env

U, T, S, W, P = 2, 60, 4, 2, 2
MAX_INC = 0.2
RNG = np.random.default_rng(3)
A = RNG.normal(size=(S, P))  # d x / d theta
B = RNG.normal(size=(S, W))


def physics(dyn_params, w_next, xhat, theta):
    """x = A theta + B w (ignores x-hat, as the physics F does)."""
    del dyn_params, xhat
    return jnp.asarray(A) @ theta + jnp.asarray(B) @ w_next


@pytest.fixture(scope="module")
def setup():
    w = RNG.normal(size=(U, T, W))
    truth = np.array([0.3, -0.6])
    x = np.einsum("sp,p->s", A, truth)[None, None] + np.einsum("sw,utw->uts", B, w)
    low, high = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    params = make_env_params(
        w, x, np.array([T, T]), low, high, None, stats=own_norm(w, x, np.array([T, T]))
    )
    dyn = as_stateful(physics)
    step_ref = increment_step_ref(dyn, params, np.zeros(P), MAX_INC)
    params = params.replace(step_ref=jnp.asarray(step_ref))
    cfg = EnvConfig(
        S, W, P, episode_length=20, action="increment", max_increment=MAX_INC
    )
    return make_tracking_env(physics, cfg), params, w, x, truth


def test_gate_is_exactly_zero_on_zero_residual_and_saturates_far_away():
    low, high, theta = jnp.array([0.0]), jnp.array([2.0]), jnp.array([1.0])
    ref = jnp.array([0.1])
    args = (low, high, 0.05, ref)
    assert apply_increment(jnp.array([0.7]), theta, jnp.zeros(3), *args) == theta
    far = apply_increment(jnp.array([1.0]), theta, jnp.full(3, 1e6), *args)
    np.testing.assert_allclose(far, 1.0 + 0.05 * 2.0, rtol=1e-6)
    half = apply_increment(jnp.array([1.0]), theta, jnp.full(3, 0.1), *args)
    np.testing.assert_allclose(half, 1.0 + 0.5 * 0.05 * 2.0, rtol=1e-6)
    edge = apply_increment(jnp.array([1.0]), jnp.array([1.99]), jnp.ones(3), *args)
    assert edge == 2.0  # clipped into the box


def test_sensitivity_of_a_linear_model_is_its_rms_slope():
    x_std = np.array([1.0, 2.0, 0.5, 1.0])
    rows = jnp.asarray(RNG.normal(size=(16, W)))
    sens = sensitivity(
        lambda w, th: physics(None, w, None, th), rows, np.zeros(P), x_std, np.ones(P)
    )
    want = np.sqrt(np.mean((A / x_std[:, None]) ** 2, axis=0))
    np.testing.assert_allclose(sens, want, rtol=1e-6)


def test_observation_layout_and_scale_invariant_direction():
    resid = jnp.array([3e-7, -4e-7, 0.0, 0.0])
    obs = increment_observation(
        resid, jnp.array([0.5, -1.0]), jnp.array([0.0, 0.5]), -jnp.ones(2), jnp.ones(2)
    )
    assert obs.shape == (S + 1 + W + P,) and obs.dtype == jnp.float32
    norm = np.sqrt(np.mean(np.square(resid)))
    np.testing.assert_allclose(obs[:S], resid / norm, rtol=1e-5)
    np.testing.assert_allclose(obs[S], (np.log10(norm) + 4) / 2, rtol=1e-5)
    np.testing.assert_allclose(obs[S + 1 :], [0.5, -1.0, 0.0, 0.5])


def test_env_predicts_then_corrects_with_the_gated_increment(setup):
    env, params, w, x, _ = setup
    obs, state = env.reset_at(params, 0, 5)
    np.testing.assert_allclose(state.theta, 0.0)  # the box centre
    # x-hat: the prediction of sample 5 with the centre theta
    np.testing.assert_allclose(state.xhat, B @ w[0, 5], rtol=1e-6)
    resid = (x[0, 5] - state.xhat) / np.asarray(params.x_std)
    np.testing.assert_allclose(obs[:S], resid / np.sqrt(np.mean(resid**2)), rtol=1e-5)
    norm = np.sqrt(np.mean(resid**2))
    gate = norm / (norm + np.asarray(params.step_ref))
    _, nxt, cost, _, info = env.step(
        jax.random.key(0), state, jnp.array([1.0, -1.0]), params
    )
    want = np.clip(MAX_INC * 2.0 * np.array([1.0, -1.0]) * gate, -1, 1)
    np.testing.assert_allclose(info["theta"], want, rtol=1e-5)
    np.testing.assert_allclose(nxt.theta, want, rtol=1e-5)
    # the cost: the prediction error of the next sample with the corrected theta
    np.testing.assert_allclose(nxt.xhat, A @ want + B @ w[0, 6], rtol=1e-5)
    got = (x[0, 6] - A @ want - B @ w[0, 6]) / np.asarray(params.x_std)
    np.testing.assert_allclose(cost, np.mean(got**2), rtol=1e-4)


def test_reset_draws_theta_over_the_box(setup):
    env, params, *_ = setup
    keys = jax.random.split(jax.random.key(1), 256)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    theta = np.asarray(state.theta)
    assert theta.min() > -1.0 and theta.max() < 1.0 and theta.std() > 0.4


def _gauss_newton_actor(params):
    """An 'actor' whose tanh(mean) is the Gauss-Newton step through the gate, for
    this linear model, read off the observation (direction, log-norm, theta)."""
    x_std = np.asarray(params.x_std)
    j = A / x_std[:, None]  # d r / d theta of the normalised residual
    pinv = jnp.asarray(np.linalg.pinv(j))
    ref = params.step_ref
    width = np.asarray(params.theta_high - params.theta_low)

    class Actor:
        def apply(self, _, obs):
            direction, log_norm = obs[:S], obs[S]
            norm = 10.0 ** (2.0 * log_norm - 4.0)
            step = pinv @ (direction * norm)  # the theta change that zeroes r
            a = step * (norm + ref) / (norm * MAX_INC * width)
            return jnp.arctanh(jnp.clip(a, -0.999, 0.999)), None

    return Actor()


def test_closed_loop_with_the_ideal_feedback_reaches_the_truth(setup):
    env, params, w, x, truth = setup
    pp = policy_params_from_env(params, None, max_increment=MAX_INC)
    assert isinstance(pp, IncrementPolicyParams)
    cal = make_policy_calibrator(_gauss_newton_actor(params), physics, pp)
    out = run_fleet(cal, jnp.asarray(w), jnp.asarray(x), jnp.ones((U, T), bool))
    theta = np.asarray(out.theta)
    np.testing.assert_allclose(theta[:, -1], np.broadcast_to(truth, (U, P)), atol=1e-8)
    # predict-correct: the first sample already moves theta from the centre
    assert np.all(np.abs(theta[:, 0]) > 0.1)
    # one-step predictions: x-hat_t = F(w_t, theta_{t-1})
    np.testing.assert_allclose(
        np.asarray(out.xhat)[:, 1:],
        np.einsum("sp,utp->uts", A, theta[:, :-1])
        + np.einsum("sw,utw->uts", B, w[:, 1:]),
        rtol=1e-6,
        atol=1e-9,
    )


def test_calibrator_reproduces_the_environment_rollout(setup):
    env, params, w, x, _ = setup
    actor = _gauss_newton_actor(params)
    pp = policy_params_from_env(params, None, max_increment=MAX_INC)
    cal = make_policy_calibrator(actor, physics, pp)
    out = run_fleet(cal, jnp.asarray(w), jnp.asarray(x), jnp.ones((U, T), bool))
    obs, state = env.reset_at(params, 1, 0)
    thetas = []
    for _ in range(10):  # a test loop over a few steps, not a hot path
        mean, _ = actor.apply(None, obs)
        obs, state, *_ = env.step(jax.random.key(0), state, jnp.tanh(mean), params)
        thetas.append(np.asarray(state.theta))
    np.testing.assert_allclose(np.asarray(out.theta)[1, :10], thetas, atol=1e-6)


def test_calibrator_carries_a_hinted_models_warm_start(setup):
    # a static model with a warm start: the calibrator threads the hint from sample
    # to sample (here a call counter) and its thetas are the plain model's
    from jaxcal.envs.memory import HintedDynamics

    env, params, w, x, _ = setup
    actor = _gauss_newton_actor(params)
    pp = policy_params_from_env(params, None, max_increment=MAX_INC)

    def step(dyn_params, hint, w_next, xhat, theta):
        return hint + 1, physics(dyn_params, w_next, xhat, theta)

    hinted = HintedDynamics(physics, step, lambda: jnp.zeros((), jnp.int32))
    mask = jnp.ones((U, T), bool)
    plain = run_fleet(make_policy_calibrator(actor, physics, pp), w, x, mask)
    cal = make_policy_calibrator(actor, hinted, pp, warm_start=True)
    out = run_fleet(cal, jnp.asarray(w), jnp.asarray(x), mask)
    np.testing.assert_array_equal(np.asarray(out.theta), np.asarray(plain.theta))
    state = cal.init(None, jnp.asarray(w[0, 0]), jnp.asarray(x[0, 0]))
    for t in range(3):
        state, _ = cal.step(state, jnp.asarray(w[0, t]), jnp.asarray(x[0, t]))
    assert int(state.hint) == 3
    # without warm_start (batched paths) the hint is neither carried nor called
    cold = make_policy_calibrator(actor, hinted, pp)
    state = cold.init(None, jnp.asarray(w[0, 0]), jnp.asarray(x[0, 0]))
    state, _ = cold.step(state, jnp.asarray(w[0, 0]), jnp.asarray(x[0, 0]))
    assert state.hint is None
    # map_output (the paper's perturbation of the model output) keeps the hint path
    doubled = hinted.map_output(lambda out: 2.0 * out)
    hint, out2 = doubled.step(None, jnp.int32(5), w[0, 0], x[0, 0], jnp.zeros(P))
    assert int(hint) == 6
    np.testing.assert_allclose(out2, 2.0 * physics(None, w[0, 0], None, jnp.zeros(P)))


class StepActor:
    """The actor of gain 1 on the step the observation holds last before the age."""

    def apply(self, _, obs):
        return jnp.arctanh(jnp.clip(obs[-P - 1 : -1], -0.999, 0.999)), None


def _unit_gain_thetas(dynamics, params, w, x, inc=MAX_INC, **flags) -> np.ndarray:
    """``[U, T, P]`` thetas of :class:`StepActor` deployed on every unit."""
    pp = policy_params_from_env(params, None, max_increment=inc, **flags)
    cal = make_policy_calibrator(StepActor(), dynamics, pp)
    out = run_fleet(cal, jnp.asarray(w), jnp.asarray(x), jnp.ones((U, T), bool))
    return np.asarray(out.theta)


def test_gauss_newton_feature_makes_a_unit_gain_the_gauss_newton_step(setup):
    # with env.gauss_newton the observation ends with the residual's Gauss-Newton
    # step in the action's scale: an actor that outputs it (gain 1) drives theta to
    # the truth, and the deployed calibrator reproduces the environment's rollout
    _, params, w, x, truth = setup
    cfg = EnvConfig(
        S, W, P, episode_length=20, action="increment", max_increment=MAX_INC,
        gauss_newton=True,
    )  # fmt: skip
    env = make_tracking_env(physics, cfg)
    assert env.observation_size == S + 1 + W + 2 * P + 1

    theta = _unit_gain_thetas(physics, params, w, x, gauss_newton=True)
    np.testing.assert_allclose(theta[:, -1], np.broadcast_to(truth, (U, P)), atol=1e-6)
    obs, state = env.reset_at(params, 1, 0)
    resid = (x[1, 0] - np.asarray(state.xhat)) / np.asarray(params.x_std)
    a = A / np.asarray(params.x_std)[:, None]
    delta = np.linalg.lstsq(a, resid, rcond=None)[0]
    width = np.asarray(params.theta_high - params.theta_low)
    scale = np.asarray(params.step_ref) / (MAX_INC * width * np.sqrt(np.mean(resid**2)))
    np.testing.assert_allclose(
        obs[-P - 1 : -1], np.clip(delta * scale, -10, 10), rtol=1e-4
    )
    assert obs[-1] == 0.0  # the window's age: its first sample
    ages = []
    thetas = []
    for _ in range(10):  # a test loop over a few steps, not a hot path
        mean, _ = StepActor().apply(None, obs)
        obs, state, *_ = env.step(jax.random.key(0), state, jnp.tanh(mean), params)
        thetas.append(np.asarray(state.theta))
        ages.append(float(obs[-1]))
    np.testing.assert_allclose(theta[1, :10], thetas, atol=1e-6)
    np.testing.assert_allclose(
        ages, np.log1p(np.arange(1, 11)) / np.log1p(32), rtol=1e-6
    )
    with pytest.raises(ValueError, match="gauss_newton needs env.action"):
        EnvConfig(S, W, P, gauss_newton=True)


def test_sensitivity_carried_gives_a_memory_models_total_derivative():
    # a linear model with memory, z' = a z + b theta, x = c z + d theta: with the
    # state's sensitivity carried from zero, the step's Jacobian is the derivative
    # of the whole rollout from a fixed z_0 with theta held (not the one-step one)
    from jaxcal.envs.increment import step_with_sensitivity

    a, b = jnp.array([[0.6]]), jnp.array([[1.0, 0.5]])
    c, d = jnp.array([[2.0], [0.0]]), jnp.array([[0.0, 0.0], [0.3, 1.0]])

    def step(z, theta):
        z_next = a @ z + b @ theta
        return z_next, c @ z_next + d @ theta

    theta, z0 = jnp.array([0.2, -0.1]), jnp.array([1.0])

    def rollout(th, n):
        z = z0
        for _ in range(n):  # a test's reference, three steps
            z, x = step(z, th)
        return x

    z, sens = z0, jnp.zeros((1, 2))
    for n in range(1, 4):
        jac, sens, z, x = step_with_sensitivity(step, z, theta, sens)
        np.testing.assert_allclose(jac, jax.jacfwd(rollout)(theta, n), rtol=1e-6)
        np.testing.assert_allclose(x, rollout(theta, n), rtol=1e-6)
    one_step, none, *_ = step_with_sensitivity(step, z, theta, None)
    assert none is None
    np.testing.assert_allclose(one_step, c @ b + d, rtol=1e-6)


A_VEC, C_VEC = np.array([1.0, 0.4]), np.array([0.2, 1.5])


def bilinear(dyn_params, w_next, xhat, theta):
    """One output, two parameters: x = (a + c w) . theta (one sample's Jacobian has
    rank 1)."""
    del dyn_params, xhat
    return ((jnp.asarray(A_VEC) + jnp.asarray(C_VEC) * w_next[0]) @ theta)[None]


def test_filter_step_identifies_what_one_sample_cannot_and_env_and_calibrator_agree():
    # one output, two parameters: x = (a + c w) . theta. One sample's Jacobian has
    # rank 1; the filter's (carried along the stream) separates the two as w
    # varies. An actor that outputs the filter step (gain 1) reaches the truth on
    # noise-free data; the covariance is the Kalman filter's (Joseph form, numpy
    # reference below) and the deployed calibrator reproduces the environment
    from jaxcal.envs.increment import FILTER_PRIOR_STD, FILTER_Q

    rng = np.random.default_rng(5)
    w = rng.uniform(-1.0, 1.0, size=(U, T, 1))
    truth = np.array([0.3, -0.6])
    x = ((A_VEC + C_VEC * w) @ truth)[..., None]
    low, high = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    params = make_env_params(
        w, x, np.array([T, T]), low, high, None, stats=own_norm(w, x, np.array([T, T]))
    )
    step_ref = increment_step_ref(as_stateful(bilinear), params, np.zeros(P), MAX_INC)
    noise = 0.01 * np.asarray(params.x_std)
    params = params.replace(step_ref=jnp.asarray(step_ref), x_noise=jnp.asarray(noise))
    cfg = EnvConfig(
        1, 1, P, episode_length=20, action="increment", max_increment=MAX_INC,
        gn_filter=True,
    )  # fmt: skip
    env = make_tracking_env(bilinear, cfg)
    assert env.observation_size == 1 + 1 + 1 + P + P + 1

    theta = _unit_gain_thetas(bilinear, params, w, x, gn_filter=True)
    np.testing.assert_allclose(theta[:, -1], np.broadcast_to(truth, (U, P)), atol=2e-3)
    obs, state = env.reset_at(params, 1, 0)
    cov = FILTER_PRIOR_STD**2 * np.eye(P)
    half = 0.5 * (high - low)
    thetas = []
    for t in range(10):  # a test loop over a few steps, not a hot path
        j = ((A_VEC + C_VEC * w[1, t, 0]) * half)[None]  # [1, P] in half-box units
        pred = cov + FILTER_Q**2 * np.eye(P)
        s = j @ pred @ j.T + np.diag(noise**2)
        gain = pred @ j.T @ np.linalg.inv(s)
        cov = (np.eye(P) - gain @ j) @ pred  # the textbook form (same in exact math)
        np.testing.assert_allclose(np.asarray(state.cov), cov, rtol=1e-3, atol=1e-7)
        mean, _ = StepActor().apply(None, obs)
        obs, state, *_ = env.step(jax.random.key(0), state, jnp.tanh(mean), params)
        thetas.append(np.asarray(state.theta))
    np.testing.assert_allclose(theta[1, :10], thetas, atol=1e-5)
    with pytest.raises(ValueError, match="needs EnvParams.x_noise"):
        env.reset_at(params.replace(x_noise=None), 0, 0)


@pytest.mark.parametrize("whole", [True, False])
def test_filter_whole_makes_a_unit_gain_the_filter_step_at_any_residual(whole):
    # filter_whole divides the increment's gate out of the filter's feature: an
    # actor of gain 1 then moves theta as the filter's mean moves (numpy Kalman
    # reference, random walk filter_q) at a residual far above the gate's scale
    # n_ref (the battery's capacity); without it (the runs before it) the step is
    # the share n_ref / (|r| + n_ref) of that. The env and the deployed calibrator
    # agree either way, and both start the filter at filter_prior_std.
    rng = np.random.default_rng(7)
    w = rng.uniform(-1.0, 1.0, size=(U, T, 1))
    truth = np.array([0.06, -0.09])
    x = ((A_VEC + C_VEC * w) @ truth)[..., None] + 0.02 * rng.normal(size=(U, T, 1))
    low, high = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    lengths = np.array([T, T])
    params = make_env_params(
        w, x, lengths, low, high, None, stats=own_norm(w, x, lengths)
    )
    noise, q, inc, prior_std = np.array([0.02]), 0.05, 1.0, 0.5
    step_ref = 0.1 * np.abs(x[1, 0] / np.asarray(params.x_std))  # |r_0| = 10 n_ref
    params = params.replace(
        step_ref=jnp.full(P, step_ref[0]), x_noise=jnp.asarray(noise)
    )
    cfg = EnvConfig(
        1, 1, P, episode_length=20, action="increment", max_increment=inc,
        gn_filter=True, filter_q=q, filter_whole=whole, filter_prior_std=prior_std,
    )  # fmt: skip
    env = make_tracking_env(bilinear, cfg)
    obs, state = env.reset_at(params, 1, 0)
    assert np.all(np.abs(obs[-P - 1 : -1]) < 0.99)  # unsaturated
    env_thetas = []
    for _ in range(10):  # a test loop over a few steps, not a hot path
        mean, _ = StepActor().apply(None, obs)
        obs, state, *_ = env.step(jax.random.key(0), state, jnp.tanh(mean), params)
        env_thetas.append(np.asarray(state.theta))
    deployed = _unit_gain_thetas(
        bilinear, params, w, x, inc, gn_filter=True, filter_q=q, filter_whole=whole,
        filter_prior_std=prior_std,
    )  # fmt: skip
    np.testing.assert_allclose(deployed[1, :10], env_thetas, atol=1e-5)

    half = 0.5 * (high - low)
    j = (A_VEC + C_VEC * w[1, 0, 0])[None] * half
    pred = (prior_std**2 + q**2) * np.eye(P)
    gain = pred @ j.T @ np.linalg.inv(j @ pred @ j.T + np.diag(noise**2))
    first = half * (gain @ x[1, 0])  # from theta = 0, the box centre
    if whole:
        np.testing.assert_allclose(env_thetas[0], first, rtol=1e-4)
    else:
        np.testing.assert_allclose(env_thetas[0], first / 11.0, rtol=1e-4)
