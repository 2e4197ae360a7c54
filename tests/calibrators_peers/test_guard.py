"""Guarded samples: no sample poisons a calibrator (issue 12, item 1).

A sample with NaN / Inf, or outside the valid box, must be skipped: the state is left
exactly as it was, the outputs repeat the last valid ones, the row is flagged, and
every other row equals (bit for bit) the stream that never saw the sample.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.agents.configs import CLACConfig
from jaxcal.agents.networks import make_networks
from jaxcal.calibrators.interface import (
    REASON_CODE,
    REASONS,
    Calibrator,
    CalStepOutput,
    Measurement,
    SampleCheck,
    count_reasons,
    run_calibrator,
    run_fleet,
    sample_reason,
)
from jaxcal.calibrators.methods.e2e.network import (
    E2EConfig,
    init_e2e_params,
    make_e2e_calibrator,
)
from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig, make_least_squares
from jaxcal.calibrators.methods.policy.calibrator import (
    PolicyParams,
    make_policy_calibrator,
)
from jaxcal.calibrators.ukf import UKFConfig, make_ukf
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.engine import ENVELOPES

NUM_STEPS, NUM_SENSORS, NUM_PARAMS = 9, 3, 2
BAD = 4  # index of the poisoned sample
CHECK = SampleCheck(
    w_low=np.array([-1.0, -1.0]),
    w_high=np.array([1.0, 1.0]),
    x_low=np.full(NUM_SENSORS, -50.0),
    x_high=np.full(NUM_SENSORS, 50.0),
)


def toy_measure(w, theta):
    """A smooth 2-parameter, 3-sensor model with 2 conditions."""
    a = jnp.array([1.0, 0.5, -0.8])
    return jnp.exp(a * theta[0]) * (1.0 + w[0]) + jnp.tanh(theta[1] + w[1])


def record(seed=0):
    rng = np.random.default_rng(seed)
    w = rng.uniform(-0.5, 0.5, (NUM_STEPS, 2))
    theta = np.stack([0.1 - 0.01 * np.arange(NUM_STEPS), -0.2 + 0.0 * w[:, 0]], 1)
    x = np.asarray(jax.vmap(toy_measure)(w, theta)) + 0.01 * rng.normal(
        size=(NUM_STEPS, NUM_SENSORS)
    )
    return w, x


def make_policy() -> Calibrator:
    actor = make_networks(CLACConfig(actor_hidden_sizes=(16,)), NUM_PARAMS).actor
    obs = jnp.zeros((1, 2 * NUM_SENSORS + 2), jnp.float32)
    params = PolicyParams(
        actor=actor.init(jax.random.key(0), obs),
        dyn_params=None,
        w_mean=jnp.zeros(2),
        w_std=jnp.ones(2),
        x_mean=jnp.ones(NUM_SENSORS),
        x_std=jnp.ones(NUM_SENSORS),
        theta_low=jnp.full(NUM_PARAMS, -0.3),
        theta_high=jnp.full(NUM_PARAMS, 0.3),
    )

    def dynamics(dyn_params, w, xhat, theta):
        del dyn_params
        return 0.8 * xhat + 0.2 * toy_measure(w, theta)

    return make_policy_calibrator(actor, dynamics, params)


def make_method(name: str) -> Calibrator:
    meas = Measurement(
        centre=jnp.zeros(NUM_SENSORS), noise_std=jnp.full(NUM_SENSORS, 0.5)
    )
    if name == "ukf":
        return make_ukf(toy_measure, UKFConfig(q=0.05, r=0.05), meas, theta0=[0.0, 0])
    if name == "least_squares":
        cfg = LeastSquaresConfig(window=3, num_iters=2)
        return make_least_squares(toy_measure, cfg, meas, theta0=[0.0, 0.0])
    if name == "e2e":
        cfg = E2EConfig(hidden_sizes=(8,))
        params = init_e2e_params(jax.random.key(1), 2, NUM_SENSORS, NUM_PARAMS, cfg)
        return make_e2e_calibrator(params, toy_measure)
    return make_policy()


RUN = jax.jit(run_calibrator, static_argnums=0)
METHODS = ["ukf", "least_squares", "e2e", "policy"]


def poison(w, x, where: str, value: float, row: int = BAD):
    w, x = w.copy(), x.copy()
    (w if where == "w" else x)[row, 1] = value
    return w, x


def assert_same_tree(a, b):
    jax.tree.map(np.testing.assert_array_equal, a, b)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    ("where", "value", "reason"),
    [
        ("x", np.inf, "x_nonfinite"),  # a NaN in one output is missing data
        ("w", np.inf, "w_nonfinite"),
        ("w", 40.0, "w_out_of_range"),
        ("x", -1e6, "x_out_of_range"),
    ],
)
def test_poisoned_stream_equals_the_stream_without_the_sample(
    method, where, value, reason
):
    cal = make_method(method)
    w, x = record()
    w_bad, x_bad = poison(w, x, where, value)
    out = RUN(cal, w_bad, x_bad, check=CHECK)
    keep = np.arange(NUM_STEPS) != BAD
    ref = RUN(cal, w[keep], x[keep], check=CHECK)
    expected_reason = np.zeros(NUM_STEPS, np.int32)
    expected_reason[BAD] = REASON_CODE[reason]
    np.testing.assert_array_equal(out.reason, expected_reason)
    np.testing.assert_array_equal(out.valid, keep)
    # Every other row: bit for bit the stream that never saw the sample.
    take = lambda a: np.asarray(a)[keep]  # noqa: E731
    assert_same_tree(
        jax.tree.map(take, (out.theta, out.xhat, out.aux)),
        jax.tree.map(np.asarray, (ref.theta, ref.xhat, ref.aux)),
    )
    # The skipped row repeats the last valid outputs; nothing is NaN.
    np.testing.assert_array_equal(out.theta[BAD], out.theta[BAD - 1])
    assert np.isfinite(np.asarray(out.theta)).all()


@pytest.mark.parametrize("method", METHODS)
def test_bad_first_sample_outputs_zeros_and_init_takes_the_first_ok_one(method):
    cal = make_method(method)
    w, x = record(seed=3)
    w_bad, x_bad = poison(w, x, "x", np.inf, row=0)
    out = RUN(cal, w_bad, x_bad)  # no box: finiteness only
    ref = RUN(cal, w[1:], x[1:])
    np.testing.assert_array_equal(out.theta[0], np.zeros(NUM_PARAMS))
    assert out.reason[0] == REASON_CODE["x_nonfinite"]
    np.testing.assert_array_equal(out.theta[1:], ref.theta)
    np.testing.assert_array_equal(out.xhat[1:], ref.xhat)


def test_old_code_would_poison_every_later_sample():
    """The unguarded step: one Inf in x reaches the UKF state for ever."""
    cal = make_method("ukf")
    w, x = record()
    w_bad, x_bad = poison(w, x, "x", np.inf)
    state = cal.init(None, w_bad[0], x_bad[0])
    thetas = []
    for t in range(NUM_STEPS):
        state, out = cal.step(state, w_bad[t], x_bad[t])
        thetas.append(out.theta)
    assert np.isnan(np.asarray(thetas[-1])).all()  # what the guard prevents
    assert np.isfinite(np.asarray(RUN(cal, w_bad, x_bad).theta)).all()


def test_a_step_that_gives_nan_is_skipped_as_state_nonfinite():
    def init(key, w0, x0):
        del key, w0
        return x0

    def step(state, w_t, x_t):
        # the "model" does not solve for w > 0.4: NaN out, as the engine does
        theta = jnp.where(w_t[0] > 0.4, jnp.nan, 1.0) * (state[:2] + x_t[:2])
        return state + x_t, CalStepOutput(theta=theta, xhat=x_t)

    w, x = record()
    w[BAD, 0] = 0.45
    keep = np.arange(NUM_STEPS) != BAD
    out = RUN(Calibrator(init, step), w, x)
    ref = RUN(Calibrator(init, step), w[keep], x[keep])
    assert REASONS[int(out.reason[BAD])] == "state_nonfinite"
    np.testing.assert_array_equal(np.asarray(out.theta)[keep], ref.theta)


def test_sample_reason_precedence_and_no_check():
    w, x = jnp.zeros(2), jnp.zeros(NUM_SENSORS)
    assert sample_reason(None, w, x) == REASON_CODE["ok"]
    assert sample_reason(None, w.at[0].set(99.0), x) == REASON_CODE["ok"]
    assert sample_reason(CHECK, w.at[0].set(99.0), x) == REASON_CODE["w_out_of_range"]
    both = sample_reason(CHECK, w.at[0].set(jnp.nan), x.at[0].set(jnp.nan))
    assert both == REASON_CODE["w_nonfinite"]  # w's check comes first
    assert sample_reason(CHECK, w, x.at[2].set(-jnp.inf)) == REASON_CODE["x_nonfinite"]
    no_x_box = CHECK._replace(x_low=None, x_high=None)
    assert sample_reason(no_x_box, w, x.at[0].set(1e9)) == REASON_CODE["ok"]


def test_from_range_widens_by_the_span_and_rejects_bad_boxes():
    check = SampleCheck.from_range([0.0, 10.0], [1.0, 30.0], [5.0], [6.0], margin=0.5)
    np.testing.assert_allclose(check.w_low, [-0.5, 0.0])
    np.testing.assert_allclose(check.w_high, [1.5, 40.0])
    np.testing.assert_allclose(check.x_low, [4.5])
    with pytest.raises(ValueError, match="w_low and w_high must be"):
        SampleCheck.from_range([1.0], [0.0])
    with pytest.raises(ValueError, match="margin must be >= 0"):
        SampleCheck.from_range([0.0], [1.0], margin=-1)


def test_envelope_box_holds_the_envelope_corners():
    env = ENVELOPES["cmapss"]
    check = SampleCheck(*env.w_box())
    for alt in env.alt_ft:
        for mach in env.mach:
            for dev in env.t2_dev_r:
                t2 = float(isa_total_temperature(alt, mach)) + dev
                w = jnp.array([alt, mach, 50.0, t2])
                assert sample_reason(check, w, jnp.zeros(1)) == REASON_CODE["ok"]
    w_far = jnp.array([0.0, 0.5, 50.0, 5000.0])
    assert sample_reason(check, w_far, jnp.zeros(1)) == REASON_CODE["w_out_of_range"]


def test_run_fleet_flags_masked_and_bad_rows_and_counts_them():
    cal = make_method("ukf")
    w, x = record()
    w_bad, x_bad = poison(w, x, "x", np.inf)
    ws, xs = np.stack([w, w_bad]), np.stack([x, x_bad])
    mask = np.ones((2, NUM_STEPS), bool)
    mask[0, -2:] = False
    out = jax.jit(run_fleet, static_argnums=0)(cal, ws, xs, mask, check=CHECK)
    assert out.reason.shape == out.valid.shape == (2, NUM_STEPS)
    assert out.reason[0, -1] == REASON_CODE["masked"]
    counts = count_reasons(out.reason, mask)
    assert counts["x_nonfinite"] == 1 and sum(counts.values()) == 1
    assert set(counts) == set(REASONS[2:])


def test_scores_use_valid_samples_only_and_count_the_flagged():
    from jaxcal.training.scoring.trajectories import score_units

    theta = np.zeros((1, 4, 1))
    theta_hat = np.array([[[0.1], [0.1], [5.0], [0.1]]])  # row 2: a held value
    x = np.ones((1, 4, 1))
    reason = np.array([[0, 0, REASON_CODE["x_nonfinite"], REASON_CODE["masked"]]])
    mask = np.array([[True, True, True, False]])
    scores = score_units(
        theta_hat, x, theta, x, mask, np.ones(1), ("s",), ("p",), reason=reason
    )
    assert scores["theta_rmse"] == pytest.approx(0.1)
    assert scores["num_samples"] == 3 and scores["num_scored"] == 2
    assert scores["num_flagged"] == 1 and scores["flagged"]["x_nonfinite"] == 1
    with pytest.raises(ValueError, match="every one of the 3 samples was flagged"):
        score_units(
            theta_hat, x, theta, x, mask, np.ones(1), ("s",), ("p",),
            reason=np.full((1, 4), REASON_CODE["w_nonfinite"]),
        )  # fmt: skip


@pytest.mark.parametrize("method", METHODS)
def test_a_missing_output_is_used_or_skipped_as_x_partial_by_the_method(method):
    """Issue 25: NaN in one output (a channel dropped out) is missing data. The UKF
    and least squares update on the other outputs; a network (E2E, a policy) cannot
    take a NaN and skips the row as ``x_partial``, exactly as if it never came."""
    cal = make_method(method)
    w, x = record()
    _, x_part = poison(w, x, "x", np.nan)
    out = RUN(cal, w, x_part, check=CHECK)
    keep = np.arange(NUM_STEPS) != BAD
    skipped = RUN(cal, w[keep], x[keep], check=CHECK)
    np.testing.assert_array_equal(out.partial, ~keep)
    assert np.isfinite(np.asarray(out.theta)).all()
    if method in ("ukf", "least_squares"):
        assert cal.accepts_partial and out.valid.all() and (out.reason == 0).all()
        # the row moved the estimate: it was used, not skipped
        assert not np.array_equal(out.theta[BAD], out.theta[BAD - 1])
        assert np.isfinite(np.asarray(out.xhat[BAD])).all()  # incl. the missing one
    else:
        assert not cal.accepts_partial
        assert REASONS[int(out.reason[BAD])] == "x_partial" and not out.valid[BAD]
        take = lambda a: np.asarray(a)[keep]  # noqa: E731
        assert_same_tree(
            jax.tree.map(take, (out.theta, out.xhat, out.aux)),
            jax.tree.map(np.asarray, (skipped.theta, skipped.xhat, skipped.aux)),
        )


def test_sample_reason_of_partial_rows():
    w, x = jnp.zeros(2), jnp.zeros(NUM_SENSORS)
    part = x.at[1].set(jnp.nan)
    code = lambda *a, **k: REASONS[int(sample_reason(*a, **k))]  # noqa: E731
    assert code(CHECK, w, part) == "x_partial"
    assert code(CHECK, w, part, partial_ok=True) == "ok"
    # an Inf is broken, not missing; a row with no output is not partial
    assert code(CHECK, w, part.at[0].set(jnp.inf), partial_ok=True) == "x_nonfinite"
    assert code(CHECK, w, x * jnp.nan, partial_ok=True) == "x_nonfinite"
    # the observed outputs of a used partial row are range-checked
    far = part.at[0].set(1e6)
    assert code(CHECK, w, far, partial_ok=True) == "x_out_of_range"
