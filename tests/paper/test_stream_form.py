"""The single-stream form of a policy on F (its solve warm-started from the previous
sample) gives the scored (cold) form's theta to the solver's tolerance."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.keys import has_prng_key

from jaxcal.calibrators.methods.policy.calibrator import (
    IncrementPolicyParams,
    make_policy_calibrator,
)
from jaxcal.envs.memory import HintedDynamics
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature

THETA = ["HPT_eff_mod", "LPT_flow_mod"]
OUTPUTS = ["T30", "T50", "Nc", "Ps30"]


class _Feedback:
    """A fixed feedback law on the observation (its first P entries: the residual
    features), deterministic and sensitive to the prediction error."""

    def apply(self, params, obs):
        del params
        return 0.5 * jnp.tanh(obs[: len(THETA)]), jnp.zeros(len(THETA))


def _flight(n=10):
    alt = np.linspace(12000.0, 15000.0, n)
    mach = np.linspace(0.42, 0.5, n)
    tra = 78.0 + 0.5 * np.sin(np.arange(n))
    return np.stack([alt, mach, tra, np.asarray(isa_total_temperature(alt, mach))], 1)


@pytest.fixture(scope="module")
def setup():
    from jaxcal.models.turbofan.model import load_turbofan
    from jaxcal.training.components import _dynamics

    with jax.enable_x64(True):
        model = load_turbofan("cmapss")
        dyn = _dynamics("physics", model, THETA, OUTPUTS, model.nominal, None)
        w = _flight()
        truth = np.asarray(model.nominal, np.float64).copy()
        index = model.parameter_index(THETA)
        truth[index] = [-0.006, -0.004]
        measure = jax.jit(model.restrict(model.parameter_names, OUTPUTS))
        x = np.stack([np.asarray(measure(w[t], truth)) for t in range(len(w))])
        params = IncrementPolicyParams(
            actor=jnp.zeros(()), dyn_params=None,
            w_mean=jnp.asarray(w.mean(0)), w_std=jnp.asarray(w.std(0) + 1.0),
            x_mean=jnp.asarray(x.mean(0)), x_std=jnp.asarray(x.std(0) + 1.0),
            theta_low=jnp.full(2, -0.02), theta_high=jnp.full(2, 0.0),
            step_ref=jnp.full(2, 1e-3), max_increment=0.1,
        )  # fmt: skip
    return dyn, params, w, x


def _stream(dyn, params, w, x, warm_start):
    cal = make_policy_calibrator(_Feedback(), dyn, params, warm_start=warm_start)
    return _run(cal, w, x)


def _run(cal, w, x):
    """theta [T, P], x-hat [T, S] and the last state of ``cal`` along (w, x)."""
    step = jax.jit(cal.step)
    with jax.enable_x64(True):
        state = cal.init(None, jnp.asarray(w[0]), jnp.asarray(x[0]))
        thetas, xhats = [], []
        for t in range(len(w)):
            state, out = step(state, jnp.asarray(w[t]), jnp.asarray(x[t]))
            thetas.append(np.asarray(out.theta))
            xhats.append(np.asarray(out.xhat))
    return np.stack(thetas), np.stack(xhats), state


@pytest.fixture(scope="module")
def warm(setup):
    """The warm-started stream ``(theta, x-hat, last state)``, run once: each stream
    traces the hinted engine afresh (~10 s)."""
    return _stream(*setup, warm_start=True)


def test_warm_stream_matches_the_scored_form(setup, warm):
    dyn, params, w, x = setup
    assert isinstance(dyn, HintedDynamics)
    theta_w, xhat_w, state_w = warm
    theta_c, xhat_c, state_c = _stream(dyn, params, w, x, warm_start=False)
    assert state_c.hint is None and bool(state_w.hint.ok)
    # the feedback moved theta: the comparison exercises the closed loop
    assert np.ptp(theta_c, axis=0).max() > 1e-4
    np.testing.assert_allclose(xhat_w, xhat_c, rtol=1e-9)
    np.testing.assert_allclose(theta_w, theta_c, rtol=0, atol=1e-9)


def test_policy_method_deploys_warm_without_a_noise_key(setup, warm):
    from types import SimpleNamespace

    from jaxcal.data.padded import Padded
    from jaxcal.paper.compare import measure_latency
    from jaxcal.paper.methods import policy_method

    dyn, params, w, x = setup
    run = SimpleNamespace(
        params=params, actor=_Feedback(), dynamics=dyn, band=None, run_dir="toy",
        step=0, problem=SimpleNamespace(),
        config=SimpleNamespace(dynamics="physics", seed=0, preset="toy"),
    )  # fmt: skip
    method = policy_method(run, "toy")
    assert method.warm
    with jax.enable_x64(True):
        cal = method.deploy()
        state = cal.init(jax.random.key(0), jnp.asarray(w[0]), jnp.asarray(x[0]))
        assert not has_prng_key(state)
        assert state.hint is not None  # the solver's warm start is carried
        np.testing.assert_array_equal(_run(cal, w, x)[0], warm[0])
        units = Padded(
            w=w[None], x=x[None], theta=np.zeros((1, len(w), 2)),
            lengths=np.array([len(w)], np.int32), unit_ids=np.array([1]),
        )  # fmt: skip
        record = measure_latency(method, units, repeats=3)
    assert record["stream_form"] and record["deploy_form"]


def test_a_fleet_carries_the_warm_start_and_each_unit_gets_its_stream(setup, warm):
    """The fleet runner carries the hinted solve along each unit (the turbofan's
    batching rule: Broyden for the batch, the cold solve only at rows where some
    unit needs it), and each unit gets the theta its own warm stream gives: a unit
    whose rows start later takes its cold first solve while the others are warm."""
    from jaxcal.calibrators.methods.policy.calibrator import make_fleet_runner

    dyn, params, w, x = setup
    late = 3  # unit 1's first rows are padding: its first solve is cold alone
    w_late = np.concatenate([w[:late], w[: len(w) - late]])
    x_late = np.concatenate([x[:late], x[: len(x) - late]])
    mask = np.ones((2, len(w)), bool)
    mask[1, :late] = False
    with jax.enable_x64(True):
        out = make_fleet_runner(_Feedback(), dyn)(
            params, np.stack([w, w_late]), np.stack([x, x_late]), mask
        )
    theta = np.asarray(out.theta)
    np.testing.assert_allclose(theta[0], warm[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(theta[1, late:], warm[0][: len(w) - late], atol=1e-12)
    assert np.asarray(out.valid)[1].tolist() == mask[1].tolist()
