"""Partial observations (issue 25): a row with some outputs missing (NaN, a sensor
channel dropped out) is read and kept, used by the UKF (update on the observed
outputs) and least squares (masked residual), flagged ``partial`` and skipped as
``x_partial`` by the methods that need every output.

The reference of the UKF is the UKF on the model restricted to the row's observed
outputs, stepped row by row from the same state: the masked update in fixed shapes
must be exactly that update.
"""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.calibrators.interface import Measurement, run_calibrator
from jaxcal.calibrators.methods.e2e.network import E2EConfig
from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig, make_least_squares
from jaxcal.calibrators.methods.ls.window_state import make_window_least_squares
from jaxcal.calibrators.ukf import UKFConfig, make_joint_ukf, make_ukf
from jaxcal.data.readers import read_dataset
from jaxcal.nets.mlp import RegressorConfig
from jaxcal.problem import Transition
from tests.support.ls_fit import FitConfig, fit_least_squares

NUM_STEPS, NUM_SENSORS = 12, 4
RUN = jax.jit(run_calibrator, static_argnums=0)
MEAS = Measurement(centre=jnp.array([1.0, 0.5, -0.2, 0.3]), noise_std=jnp.full(4, 0.4))
THETA0, SCALE = jnp.array([0.1, -0.1]), jnp.array([0.5, 1.5])


def measure(w, theta):
    """A smooth 2-parameter, 4-output model of 1 condition."""
    a = jnp.array([1.0, 0.5, -0.8, 0.3])
    b = jnp.array([0.2, -1.0, 0.4, 0.9])
    return jnp.exp(a * theta[0]) * (1.0 + w[0]) + jnp.tanh(b * theta[1] + w[0])


def init_state(w0, theta):
    return jnp.stack([w0[0] * theta[0]])


def step_state(z, w, theta):
    """A model with one hidden state: a leaky integrator of the condition."""
    z_next = 0.7 * z + theta[0] * w[0] + 0.1 * theta[1]
    x = jnp.concatenate(
        [z_next, z_next * theta[1] + w[0], jnp.sin(theta[:1]) + 0.1 * z_next**2,
         theta[1:] * w[0] + z_next]
    )  # fmt: skip
    return z_next, x


STATEFUL = Transition(init_state, step_state, 1)


def restricted(observed):
    """The static model and the stateful one on the outputs ``observed`` only."""
    idx = np.flatnonzero(observed)
    meas = Measurement(centre=MEAS.centre[idx], noise_std=MEAS.noise_std[idx])

    def step(z, w, theta):
        z_next, x = step_state(z, w, theta)
        return z_next, x[idx]

    return (lambda w, th: measure(w, th)[idx]), Transition(init_state, step, 1), meas


def record(stateful=False, seed=0):
    """Noisy outputs of drifting parameters, with missing outputs: row 0 and five
    others partial (one or two outputs missing), the rest complete."""
    rng = np.random.default_rng(seed)
    w = rng.uniform(-0.5, 0.5, (NUM_STEPS, 1))
    theta = np.stack([0.2 - 0.01 * np.arange(NUM_STEPS), np.full(NUM_STEPS, -0.3)], 1)
    if stateful:
        z = np.asarray(init_state(w[0], theta[0]))
        x = []
        for t in range(NUM_STEPS):
            z, x_t = step_state(z, w[t], theta[t])
            x.append(np.asarray(x_t))
        x = np.stack(x)
    else:
        x = np.asarray(jax.vmap(measure)(w, theta))
    x = x + 0.02 * rng.normal(size=x.shape)
    # two patterns (one compiled reference each): output 1 missing, outputs 0 and 3
    for row, cols in [(0, [1]), (2, [0, 3]), (3, [1]), (6, [0, 3]), (7, [1]), (9, [1])]:
        x[row, cols] = np.nan
    return w, x


def test_ukf_on_a_partial_row_is_the_ukf_on_its_observed_outputs():
    cfg = UKFConfig(q=0.05, r=0.1, prior_std=0.7, return_cov=True)
    w, x = record()
    ukf = make_ukf(measure, cfg, MEAS, theta0=THETA0, theta_scale=SCALE)
    assert ukf.accepts_partial
    out = RUN(ukf, w, x)
    assert out.valid.all() and out.partial.sum() == 6
    state = ukf.init(None, w[0], jnp.zeros(NUM_SENSORS))

    @functools.cache
    def sub_step(observed: tuple):  # one compiled reference step per pattern
        sub_measure, _, sub_meas = restricted(np.array(observed))
        sub = make_ukf(sub_measure, cfg, sub_meas, theta0=THETA0, theta_scale=SCALE)
        return jax.jit(sub.step)

    for t in range(NUM_STEPS):
        observed = ~np.isnan(x[t])
        state, ref = sub_step(tuple(observed))(state, w[t], x[t, observed])
        np.testing.assert_allclose(out.theta[t], ref.theta, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            out.aux["theta_cov"][t], ref.aux["theta_cov"], rtol=0, atol=1e-12
        )
        np.testing.assert_allclose(
            out.aux["log_likelihood"][t], ref.aux["log_likelihood"], rtol=1e-12
        )
        np.testing.assert_allclose(
            out.aux["innovation"][t][observed], ref.aux["innovation"], atol=1e-12
        )
        assert np.all(out.aux["innovation"][t][~observed] == 0.0)
        np.testing.assert_allclose(out.xhat[t][observed], ref.xhat, atol=1e-12)
    # xhat predicts the missing outputs too: F(w, theta_t) in every column
    full = jax.vmap(measure)(w, out.theta)
    np.testing.assert_allclose(out.xhat, full, atol=1e-12)


def test_joint_ukf_on_a_partial_row_is_the_joint_ukf_on_its_observed_outputs():
    cfg = UKFConfig(q=0.05, r=0.1, prior_std=0.7, return_cov=True)
    opts = dict(theta0=THETA0, theta_scale=SCALE, state_std=0.2, state_q=0.01)
    w, x = record(stateful=True, seed=1)
    ukf = make_joint_ukf(STATEFUL, cfg, MEAS, **opts)
    out = RUN(ukf, w, x)
    assert out.valid.all() and out.partial.sum() == 6
    state = ukf.init(None, w[0], jnp.zeros(NUM_SENSORS))

    @functools.cache
    def sub_step(observed: tuple):  # one compiled reference step per pattern
        _, sub_transition, sub_meas = restricted(np.array(observed))
        return jax.jit(make_joint_ukf(sub_transition, cfg, sub_meas, **opts).step)

    for t in range(NUM_STEPS):
        observed = ~np.isnan(x[t])
        state, ref = sub_step(tuple(observed))(state, w[t], x[t, observed])
        np.testing.assert_allclose(out.theta[t], ref.theta, rtol=0, atol=1e-12)
        for name in ("theta_cov", "state", "state_std", "log_likelihood"):
            np.testing.assert_allclose(
                out.aux[name][t], ref.aux[name], rtol=1e-10, atol=1e-12
            )


def test_ukf_step_compiles_once_for_every_missing_pattern():
    ukf = make_ukf(measure, UKFConfig(), MEAS, theta0=THETA0)
    w, x = record()
    chex.clear_trace_counter()
    step = jax.jit(chex.assert_max_traces(ukf.step, n=1))
    state = ukf.init(None, w[0], jnp.zeros(NUM_SENSORS))
    for t in range(4):  # partial, complete, two missing, one missing
        state, out = step(state, w[t], x[t])
    chex.assert_tree_all_finite((state, out.theta))


def _masked_cost(theta, w, x, sigma):
    resid = (np.asarray(jax.vmap(measure, (0, None))(w, theta)) - x) / sigma
    return 0.5 * np.nansum(resid**2)


def test_least_squares_leaves_missing_outputs_out_of_the_residual():
    """Mixed pattern: the window's cost is the masked sum of squares; a column
    missing on every row is the fit of the model without it."""
    cfg = LeastSquaresConfig(window=4, num_iters=3, r=0.1)
    ls = make_least_squares(measure, cfg, MEAS, theta0=THETA0, theta_scale=SCALE)
    assert ls.accepts_partial
    w, x = record(seed=2)
    out = RUN(ls, w, x)
    assert out.valid.all() and np.isfinite(np.asarray(out.theta)).all()
    sigma = np.asarray(MEAS.noise_std) * cfg.r
    for t in range(NUM_STEPS):
        rows = slice(max(0, t - cfg.window + 1), t + 1)
        cost = _masked_cost(out.theta[t], w[rows], x[rows], sigma)
        np.testing.assert_allclose(out.aux["cost"][t], cost, rtol=1e-10)
    np.testing.assert_allclose(
        out.xhat, jax.vmap(measure)(w, out.theta), rtol=1e-10, atol=1e-12
    )
    # one output missing everywhere == least squares on the other three
    x_drop = record(seed=2)[1]
    x_drop[:, 2] = np.nan
    observed = np.array([True, True, False, True])
    x_drop[:, observed] = np.nan_to_num(x_drop[:, observed], nan=0.3)
    sub_measure, _, sub_meas = restricted(observed)
    sub = make_least_squares(
        sub_measure, cfg, sub_meas, theta0=THETA0, theta_scale=SCALE
    )
    got, ref = RUN(ls, w, x_drop), RUN(sub, w, x_drop[:, observed])
    np.testing.assert_allclose(got.theta, ref.theta, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(got.aux["cost"], ref.aux["cost"], rtol=1e-10)


def test_window_least_squares_on_a_missing_column_is_the_fit_without_it():
    cfg = LeastSquaresConfig(window=4, num_iters=3, r=0.1, prior_std=1.0)
    opts = dict(theta0=THETA0, theta_scale=SCALE, state_std=0.2)
    w, x = record(stateful=True, seed=3)
    observed = np.array([True, False, True, True])
    x[:, ~observed] = np.nan
    x[:, observed] = np.nan_to_num(x[:, observed], nan=0.3)
    cal = make_window_least_squares(STATEFUL, cfg, MEAS, **opts)
    assert cal.accepts_partial
    _, sub_transition, sub_meas = restricted(observed)
    sub = make_window_least_squares(sub_transition, cfg, sub_meas, **opts)
    got, ref = RUN(cal, w, x), RUN(sub, w, x[:, observed])
    assert got.valid.all() and got.partial.all()
    np.testing.assert_allclose(got.theta, ref.theta, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(got.aux["state"], ref.aux["state"], rtol=1e-10)
    np.testing.assert_allclose(got.xhat[:, observed], ref.xhat, rtol=1e-10)


def test_batch_fit_masks_missing_outputs():
    w, x = record(seed=4)
    out, info = fit_least_squares(measure, w, x, THETA0, FitConfig(), measurement=MEAS)
    assert bool(info.converged) and np.isfinite(np.asarray(out)).all()
    cost = _masked_cost(out, w, x, np.asarray(MEAS.noise_std))
    np.testing.assert_allclose(info.cost, cost, rtol=1e-10)
    num_resid = np.sum(~np.isnan(x))  # the noise estimate counts observed values
    expected = (
        2
        * cost
        / (num_resid - 2)
        * np.linalg.inv(_jtj(out, w, x, np.asarray(MEAS.noise_std)))
    )
    np.testing.assert_allclose(info.cov, expected, rtol=1e-6)


def _jtj(theta, w, x, std):
    jac = np.asarray(jax.vmap(jax.jacfwd(measure, 1), (0, None))(w, theta))
    jac = np.where(np.isnan(x)[..., None], 0.0, jac / std[:, None])
    jac = jac.reshape(-1, jac.shape[-1])
    return jac.T @ jac


# ------------------------------------------------------------ the front door


def tank(w, theta):
    heat, inflow = w[0], w[1]
    level = inflow / theta[0]
    return jnp.stack([level, 20.0 + heat / (inflow * (1.0 + theta[1])), theta[0]])


MODEL = jaxcal.Model.from_function(
    tank,
    conditions={"heat": "kW", "inflow": "kg/s"},
    parameters={"leak": (1.0, 0.5, 2.0), "loss": (0.1, 0.0, 0.5)},
    outputs={"level": "m", "temp": "degC", "leak_rate": "1/s"},
    condition_range=([0.0, 0.1], [50.0, 5.0]),
    name="tank_partial",
)
NOISE = {"level": 0.02, "temp": 0.02, "leak_rate": 0.02}
PARTIAL_ROWS = [3, 10, 11, 30]  # row 3 is unit 0's fourth row (file order)


@pytest.fixture(scope="module")
def frame():
    rng = np.random.default_rng(0)
    n, length = 40, 20
    frame = pd.DataFrame(
        {"heat": rng.uniform(5, 30, n), "inflow": rng.uniform(0.5, 2.0, n)}
    )
    theta = np.stack([np.full(n, 1.3), np.full(n, 0.2)], 1)
    x = np.asarray(jax.vmap(tank)(frame.to_numpy(), theta))
    x = x + 0.02 * rng.standard_normal(x.shape)
    for j, name in enumerate(MODEL.output_names):
        frame[name] = x[:, j]
    frame["unit"], frame["time"] = np.repeat([0, 1], length), np.tile(range(length), 2)
    frame.loc[3, "temp"] = np.nan
    frame.loc[10, ["level", "leak_rate"]] = np.nan
    frame.loc[11, "leak_rate"] = np.nan
    frame.loc[30, "level"] = np.nan
    return frame


def test_reader_keeps_partial_rows_and_refuses_the_rest(frame, tmp_path):
    path = tmp_path / "p.csv"
    frame.to_csv(path, index=False)
    data = read_dataset(path, MODEL)  # nonfinite="error": partial rows are not errors
    assert data.num_rows == len(frame) and not data.dropped
    np.testing.assert_array_equal(np.flatnonzero(data.partial), PARTIAL_ROWS)
    assert np.isnan(data.x[3, 1]) and np.isfinite(data.x[3, [0, 2]]).all()
    bad = frame.copy()
    bad.loc[5, "heat"] = np.nan  # a condition: as before
    bad.loc[6, list(MODEL.output_names)] = np.nan  # no output left: as before
    bad.loc[7, "temp"] = np.inf  # broken, not missing: as before
    bad.to_csv(path, index=False)
    with pytest.raises(ValueError, match="3 of 40 lines; column heat: 1 line"):
        read_dataset(path, MODEL)
    data = read_dataset(path, MODEL, nonfinite="drop")
    assert data.num_rows == len(frame) - 3 and data.partial.sum() == 4
    assert data.dropped == {"heat": 1, "level": 1, "temp": 2, "leak_rate": 1}


@pytest.mark.parametrize("method", ["ukf", "ls"])
def test_front_door_uses_partial_rows_and_flags_them(frame, method):
    options = {"window": 4} if method == "ls" else {}
    result = jaxcal.calibrate(MODEL, frame, method=method, noise=NOISE, **options)
    assert result.valid.all() and (result.reason == "ok").all()
    np.testing.assert_array_equal(np.flatnonzero(result.partial), PARTIAL_ROWS)
    assert result.num_partial == {"used": 4, "skipped": 0}
    assert result.num_flagged == {}  # a used partial row is not a skipped one
    table = result.to_frame()
    assert table["partial"].tolist() == result.partial.tolist()
    # row 3 updated the estimate on level and leak_rate (not a held row)
    assert not np.array_equal(result.theta[3], result.theta[2])
    assert np.isfinite(result.xhat).all()  # the model's value of the missing ones
    assert abs(result.theta[19, 0] - 1.3) < 0.05


def test_noise_estimate_and_box_leave_missing_outputs_out(frame):
    result = jaxcal.calibrate(MODEL, frame, method="ukf")
    assert np.isfinite(result.problem.noise_std).all()
    assert np.isfinite(result.problem.norm.x_mean).all()
    assert np.isfinite(result.problem.input_range.x_low).all()
    empty = frame.drop(index=10)  # (a row with no output left is refused)
    empty["temp"] = np.nan
    with pytest.raises(ValueError, match=r"output column\(s\) \['temp'\] hold no"):
        jaxcal.calibrate(MODEL, empty, method="ukf", noise=NOISE)


def test_e2e_skips_partial_rows_as_x_partial(frame):
    cfg = E2EConfig(
        hidden_sizes=(8,),
        fit=RegressorConfig(learning_rate=1e-3, batch_size=64, num_epochs=1,
                            validation_fraction=0.1, patience=1),
    )  # fmt: skip
    result = jaxcal.calibrate(
        MODEL, frame, method="e2e", noise=NOISE, e2e_config=cfg, e2e_copies=1
    )
    np.testing.assert_array_equal(np.flatnonzero(~result.valid), PARTIAL_ROWS)
    assert set(result.reason[PARTIAL_ROWS]) == {"x_partial"}
    assert result.num_partial == {"used": 0, "skipped": 4}
    assert result.num_flagged == {"x_partial": 4}
    np.testing.assert_array_equal(result.theta[3], result.theta[2])  # held


def test_training_leaves_partial_rows_out_and_the_diagnosis_uses_them(frame):
    """What the rest of the library does with a partial row: a policy's training
    data refuse it (or drop it, nonfinite="drop"); the diagnosis keeps it and leaves
    only its missing outputs out of the residual (issue 24), and says so."""
    from jaxcal.diagnosis.data.prepare import prepare_data
    from jaxcal.training.data.tables import load_table_data

    opts = dict(theta=("leak",), test_units=[1])
    with pytest.raises(ValueError, match="column temp: 1 row"):
        load_table_data(frame, MODEL, **opts)
    train = load_table_data(frame, MODEL, nonfinite="drop", **opts)
    assert np.isfinite(train.train.x).all()
    loop = prepare_data(read_dataset(frame, MODEL), MODEL)
    missing = int(np.isnan(frame[list(loop.sensor_names)].to_numpy()).sum())
    assert loop.num_rows == len(frame) and missing > 0
    assert int((~loop.observed).sum()) == missing
    assert np.isfinite(loop.x).all()  # a missing entry holds 0, masked out
    assert any("some outputs missing" in n for n in loop.notes)


def test_a_partial_row_beside_an_outlier_keeps_the_rest_of_the_stream():
    """The screening's outputs' centre without the outlier rows is a NaN-aware mean:
    a missing output elsewhere once made it NaN and every row ``state_nonfinite``."""
    import sys

    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from test_compile_once import MEMORY, _data

    frame = _data(MEMORY, 0)
    frame.loc[13, "y2"] = np.nan
    frame.loc[50, "y1"] += 5.0  # a wild reading: the screen flags it
    noise = {"y1": 0.01, "y2": 0.01}
    with pytest.warns(UserWarning):
        result = jaxcal.calibrate(MEMORY, frame, "ukf", noise=noise, progress=False)
    reason = np.asarray(result.reason)
    assert reason[50] == "outlier"
    assert not np.any(reason == "state_nonfinite")
    assert reason[13] == "ok" and np.isfinite(result.theta).all()
