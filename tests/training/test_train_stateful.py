"""Training, evaluation and deployment of a policy on a model with memory.

The model is defined here, as a user would, with ``jaxcal.Model.from_step``: a
first-order lag z' = a z + (1 - a) u (Z = 1) whose state no output measures
directly (y1 = k z' + v / 2, y2 = k v - z'), two calibrated parameters (a, k). The
policy trains on the model's own step (``dynamics=physics``: the surrogate cannot
carry a hidden state and says so), the environment carrying z.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from support.norm import own_norm

import jaxcal
from jaxcal.cli.evaluate import main as evaluate_main
from jaxcal.cli.train import main as train_main
from jaxcal.deploy import StreamingCalibrator
from jaxcal.envs.memory import StatefulDynamics, as_stateful, reference_states
from jaxcal.envs.tracking import (
    EnvConfig,
    EnvState,
    make_env_params,
    make_tracking_env,
)
from jaxcal.training.components import make_dynamics


def _lag(z, w, theta):
    """z' = a z + (1 - a) u; outputs mix z' with v and the gain k."""
    a, k = theta[0], theta[1]
    u, v = w[0], w[1]
    z_next = a * z + (1.0 - a) * u
    return z_next, jnp.stack([k * z_next[0] + 0.5 * v, k * v - z_next[0]])


MODEL = jaxcal.Model.from_step(
    _lag,
    init_state=lambda w0, theta: w0[:1],  # at rest at the first input
    states=("z",),
    conditions={"u": "-", "v": "-"},
    parameters={"a": (0.7, 0.3, 0.95, "-"), "k": (1.0, 0.5, 2.0, "-")},
    outputs=("y1", "y2"),
    name="lag",
)
SPEC = f"{__file__}:MODEL"
NUM_UNITS, NUM_ROWS, NOISE = 7, 60, 0.02
# (a, k) per unit; the test unit 7 lies inside the training units' range
A = (0.6, 0.85, 0.65, 0.8, 0.7, 0.75, 0.72)
K = (0.9, 1.4, 1.3, 1.0, 1.2, 1.1, 1.15)


def _simulate(w, theta):
    """x [T, S] and z [T, 1] (state after each sample) of one unit, lax.scan."""
    z0 = MODEL.init_state(w[0], theta[0])

    def body(z, inputs):
        z_next, x, _ = MODEL.step(z, *inputs)
        return z_next, (x, z_next)

    _, (x, z) = jax.lax.scan(body, z0, (w, theta))
    return np.asarray(x), np.asarray(z)


def _frame(seed: int = 0) -> pd.DataFrame:
    """7 units of 60 rows: a step-like input u (so the lag matters), a drifting v,
    a and k constant per unit, noise std NOISE on both outputs."""
    rng = np.random.default_rng(seed)
    rows = []
    for unit in range(1, NUM_UNITS + 1):
        t = np.arange(NUM_ROWS)
        u = np.repeat(rng.uniform(0.0, 2.0, NUM_ROWS // 5), 5)
        v = 1.0 + 0.3 * np.sin(0.2 * t + unit)
        a, k = np.full(NUM_ROWS, A[unit - 1]), np.full(NUM_ROWS, K[unit - 1])
        w, theta = np.stack([u, v], 1), np.stack([a, k], 1)
        x, _ = _simulate(jnp.asarray(w), jnp.asarray(theta))
        x = x + NOISE * rng.standard_normal(x.shape)
        rows.append(
            pd.DataFrame(
                {"unit": unit, "time": t, "u": u, "v": v, "y1": x[:, 0],
                 "y2": x[:, 1], "a": a, "k": k}
            )
        )  # fmt: skip
    return pd.concat(rows, ignore_index=True)


def _argv(csv, runs, *extra):
    # The smoke preset's networks and env, trained 4 chunks of 500 steps (about
    # 1,900 updates) instead of 2 of 25: a few seconds for this tiny model.
    return [
        f"model={SPEC}", f"data={csv}", "theta=a,k", "preset=smoke",
        "dynamics=physics", "runner.num_steps_per_chunk=500", "budget.num_chunks=4",
        f"output.runs_dir={runs}", "output.progress=false", *extra,
    ]  # fmt: skip


@pytest.fixture(scope="module")
def csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("lag") / "lag.csv"
    _frame().to_csv(path, index=False)
    return path


@pytest.fixture(scope="module")
def trained(csv, tmp_path_factory):
    runs = tmp_path_factory.mktemp("runs")
    assert train_main(_argv(csv, runs, "name=lag")) == 0
    return runs / "lag"


# Tracking RMSE / noise std the trained policy must reach on the test unit, per
# output. Measured (seed 0, this command): 1.14 (y1) and 0.90 (y2), i.e. at the noise
# floor (1 would be a perfect model output against noisy data); the same run with the
# smoke budget (26 updates) gives 5.2 and 4.0. K = 2 leaves room for platform
# rounding and fails a policy that does not track.
K_NOISE = 2.0


def test_policy_on_a_model_with_memory_tracks_to_the_noise_floor(trained, csv):
    final = json.loads((trained / "final.json").read_text())
    assert final["dynamics"] == "physics" and final["test_units"] == [7]
    ratio = {k: v / NOISE for k, v in final["test"]["tracking_rmse_units"].items()}
    assert set(ratio) == {"y1", "y2"}
    assert max(ratio.values()) <= K_NOISE, ratio
    # measured 0.012 (a in [0.6, 0.85], k in [0.9, 1.4] over the units)
    assert final["test"]["theta_rmse"] < 0.05


def test_evaluate_and_streaming_deployment_carry_the_state(trained, csv, capsys):
    capsys.readouterr()
    assert evaluate_main([f"run={trained}", "repeats=1"]) == 0
    assert "theta RMSE" in capsys.readouterr().out
    cal = StreamingCalibrator(trained)
    frame = _frame()
    unit = frame[frame.unit == 7]
    w, x = unit[["u", "v"]].to_numpy(), unit[["y1", "y2"]].to_numpy()
    streamed = np.array([cal.step(w_t, x_t) for w_t, x_t in zip(w, x, strict=True)])
    theta, xhat = cal.run(w[None], x[None])
    # sample by sample (guarded, state carried on the host) == the batch scan
    np.testing.assert_allclose(streamed, theta[0], atol=1e-6)
    ratio = np.sqrt(np.mean((xhat[0] - x) ** 2, axis=0)) / NOISE
    assert np.all(ratio <= K_NOISE), ratio
    # a flagged sample leaves the carried state untouched: the stream continues
    # exactly as if it had never arrived
    cal.reset()
    for t in range(10):
        cal.step(w[t], x[t])
        if t == 4:
            cal.step(w[t] * np.nan, x[t])
            assert not cal.last_valid
    np.testing.assert_allclose(cal.step(w[10], x[10]), theta[0, 10], atol=1e-6)


def test_surrogate_is_refused_for_a_model_with_memory(csv, tmp_path, capsys):
    argv = [a for a in _argv(csv, tmp_path, "name=sur") if a != "dynamics=physics"]
    assert train_main(argv) == 2
    assert "use dynamics=physics" in capsys.readouterr().err
    assert not (tmp_path / "sur").exists()


def _unit_three():
    """``(w [1, T, 2], noisy x [1, T, 2], true theta, problem)`` of unit 3."""
    frame = _frame()
    unit = frame[frame.unit == 3]
    w = unit[["u", "v"]].to_numpy()[None]
    x_noisy = unit[["y1", "y2"]].to_numpy()[None]
    problem = jaxcal.Problem.build(
        MODEL, jaxcal.read_dataset(frame, MODEL), theta=("a", "k")
    )
    return w, x_noisy, np.array([A[2], K[2]]), problem


def test_env_carries_the_model_state():
    """With theta at the truth, the env's x-hat is the model's output exactly: z is
    taken from the reference track at the episode start and advanced every step."""
    w, x_noisy, truth, problem = _unit_three()
    x_clean, z_true = _simulate(jnp.asarray(w[0]), jnp.tile(truth, (NUM_ROWS, 1)))
    # the run's physics transition (its first state: z_0 = u_0, whatever theta)
    dyn = make_dynamics("physics", problem)
    assert isinstance(dyn, StatefulDynamics) and dyn.num_states == 1
    lengths = np.array([NUM_ROWS])
    z_ref = reference_states(dyn, None, w, x_noisy, lengths, truth)
    np.testing.assert_allclose(z_ref[0], z_true, rtol=1e-6)
    params = make_env_params(
        w, x_noisy, lengths, np.array([0.3, 0.5]), np.array([0.95, 2.0]), None,
        stats=own_norm(w, x_noisy, lengths), z_ref=z_ref,
    )  # fmt: skip
    env = make_tracking_env(dyn, EnvConfig(2, 2, 2, episode_length=20))
    action = 2.0 * (truth - params.theta_low) / (params.theta_high - params.theta_low)
    action = action - 1.0

    def rollout(start):
        obs, state = env.reset_at(params, 0, start)

        def body(state, _):
            _, state, _, _, _ = env.step(None, state, action, params)
            return state, (state.xhat, state.z)

        return jax.lax.scan(body, state, None, length=20)[1]

    xhat, z = jax.jit(rollout)(17)
    np.testing.assert_allclose(xhat, x_clean[18:38], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(z, z_true[18:38], rtol=1e-5, atol=1e-6)
    # the env refuses params without the states its dynamics carry
    with pytest.raises(ValueError, match="z_ref"):
        env.reset_at(dataclasses.replace(params, z_ref=None), 0, 0)


def _static_dynamics(dyn_params, w_next, xhat, theta):
    return 0.5 * xhat + dyn_params @ theta + jnp.sum(w_next)


def test_static_env_transitions_are_those_of_before():
    """Z = 0: the same rollout as the environment before it carried a state.

    The golden numbers were produced by the previous ``envs/tracking.py`` (commit
    f0cac47) on this exact set-up; the state is the plain four-leaf ``EnvState``, so
    the runner's checkpoints keep their layout (older runs resume).
    """
    rng = np.random.default_rng(0)
    w = rng.normal(size=(2, 8, 2)).astype(np.float32)
    x = (rng.normal(size=(2, 8, 2)) + 3.0).astype(np.float32)
    params = make_env_params(
        w, x, np.array([8, 7]), np.zeros(2, np.float32), np.ones(2, np.float32),
        jnp.asarray(rng.normal(size=(2, 2)), jnp.float32),
        stats=own_norm(w, x, np.array([8, 7])),
    )  # fmt: skip
    assert params.z_ref is None
    env = make_tracking_env(_static_dynamics, EnvConfig(2, 2, 2, episode_length=5))
    assert as_stateful(_static_dynamics).num_states == 0
    actions = jnp.linspace(-1.0, 1.0, 10).reshape(5, 2)

    def rollout(key):
        obs, state = env.reset(key, params)

        def body(carry, action):
            obs, state, cost, done, _ = env.step(key, carry[1], action, params)
            return (obs, state), (state.xhat, cost, done)

        return jax.lax.scan(body, (obs, state), actions)[1]

    keys = jax.random.split(jax.random.key(3), 2)
    xhat, cost, done = jax.jit(jax.vmap(rollout))(keys)
    golden_cost = [
        [0.93053955, 1.6970648, 0.68461925, 5.563938, 15.287191],
        [2.3562524, 0.048256077, 0.17383328, 2.2849638, 4.493639],
    ]
    golden_xhat = [[-0.8500057, 3.368403], [-0.8090751, 3.3722525]]
    np.testing.assert_allclose(cost, golden_cost, rtol=1e-6)
    np.testing.assert_allclose(xhat[:, -1], golden_xhat, rtol=1e-6)
    assert np.asarray(done)[:, -1].all() and not np.asarray(done)[:, :-1].any()
    state = env.reset(keys[0], params)[1]
    assert type(state) is EnvState and len(jax.tree.leaves(state)) == 4


def test_calibrate_front_runs_the_trained_policy_on_the_model_with_memory(trained, csv):
    """``jaxcal.calibrate(model, data, "policy", run=...)``: the same rows as the
    deployed calibrator's batch run, theta and names from the run."""
    result = jaxcal.calibrate(MODEL, csv, "policy", run=trained)
    frame = _frame()
    assert result.theta.shape == (len(frame), 2) and result.valid.all()
    unit = (frame.unit == 7).to_numpy()
    w, x = frame[unit][["u", "v"]].to_numpy(), frame[unit][["y1", "y2"]].to_numpy()
    theta, _ = StreamingCalibrator(trained).run(w[None], x[None])
    np.testing.assert_allclose(result.theta[unit], theta[0], atol=1e-6)


@pytest.mark.parametrize(
    "gn_filter,whole", [(False, False), (True, False), (True, True)]
)
def test_gauss_newton_feedback_on_a_model_with_memory_env_and_deployment_agree(
    gn_filter, whole
):
    """env.gauss_newton on a model with memory: an actor that takes the observed
    Gauss-Newton step (the state's sensitivity carried; with ``gn_filter`` the
    filter's step, which the observation holds last before the age; with
    ``filter_whole`` the joint filter of state and theta) drives theta to
    the truth on noise-free data, and the deployed calibrator reproduces the env's
    thetas."""
    from jaxcal.calibrators.interface import run_fleet
    from jaxcal.calibrators.methods.policy.calibrator import make_policy_calibrator
    from jaxcal.calibrators.methods.policy.params import policy_params_from_env
    from jaxcal.envs.increment import increment_step_ref

    w, _, truth, problem = _unit_three()
    x_clean, _ = _simulate(jnp.asarray(w[0]), jnp.tile(truth, (NUM_ROWS, 1)))
    dyn = make_dynamics("physics", problem)
    lengths = np.array([NUM_ROWS])
    x = x_clean[None]
    low, high = np.array([0.3, 0.5]), np.array([0.95, 2.0])
    z_ref = reference_states(dyn, None, w, x, lengths, problem.theta_prior)
    params = make_env_params(
        w, x, lengths, low, high, None, stats=own_norm(w, x, lengths), z_ref=z_ref
    )
    step_ref = increment_step_ref(dyn, params, problem.theta_prior, 0.2)
    noise = jnp.asarray(0.01 * np.asarray(params.x_std))
    params = params.replace(step_ref=jnp.asarray(step_ref), x_noise=noise)
    cfg = EnvConfig(
        2, 2, 2, episode_length=20, action="increment", max_increment=0.2,
        gauss_newton=True, gn_filter=gn_filter, filter_whole=whole,
    )  # fmt: skip
    env = make_tracking_env(dyn, cfg)

    class Actor:  # gain 1/2 on the Gauss-Newton step
        def apply(self, _, obs):
            return jnp.arctanh(jnp.clip(0.5 * obs[-3:-1], -0.999, 0.999)), None

    pp = policy_params_from_env(
        params, None, max_increment=0.2, gauss_newton=True, gn_filter=gn_filter,
        filter_whole=whole,
    )  # fmt: skip
    cal = make_policy_calibrator(Actor(), dyn, pp)
    mask = jnp.ones((1, NUM_ROWS), bool)
    out = run_fleet(cal, jnp.asarray(w), jnp.asarray(x), mask)
    theta = np.asarray(out.theta)[0]
    np.testing.assert_allclose(theta[-1], truth, atol=1e-3)
    obs, state = env.reset_at(params, 0, 0)
    assert state.sens.shape == (1, 2)
    assert (getattr(state, "cov", None) is not None) == gn_filter
    thetas = []
    for _ in range(8):  # a test loop over a few steps, not a hot path
        mean, _ = Actor().apply(None, obs)
        obs, state, *_ = env.step(None, state, jnp.tanh(mean), params)
        thetas.append(np.asarray(state.theta))
    np.testing.assert_allclose(theta[:8], thetas, rtol=1e-5, atol=1e-6)
