"""The one Levenberg–Marquardt core: exact answers, its rules, jit, vmap, box, hint."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.numerics.levenberg_marquardt import (
    Damping,
    Tolerance,
    gauss_newton_cov,
    inverse_psd,
    is_accepted,
    linearize,
    lm_init,
    lm_iterate,
    lm_run,
    lm_solve,
    next_damping,
)

SCHEDULE = Damping()
TIMES = jnp.linspace(0.0, 2.0, 12)


def _exp_residual(y):
    """Noise-free ``a exp(b t)`` with a = 2, b = -0.7: a nonlinear, identifiable fit."""
    return y[0] * jnp.exp(y[1] * TIMES) - 2.0 * jnp.exp(-0.7 * TIMES)


def test_a_linear_problem_gives_the_least_squares_solution_and_its_covariance():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(30, 4))
    b = rng.normal(size=30)
    resid_jac = linearize(lambda y: jnp.asarray(a) @ y - jnp.asarray(b))
    state, stats = lm_solve(resid_jac, jnp.zeros(4), Tolerance(), SCHEDULE)
    np.testing.assert_allclose(state.y, np.linalg.lstsq(a, b)[0], rtol=1e-9)
    assert int(stats.status) == 1
    np.testing.assert_allclose(
        gauss_newton_cov(state.jac), np.linalg.inv(a.T @ a), rtol=1e-9
    )


@pytest.mark.parametrize("transform", [lambda f: f, jax.jit], ids=["eager", "jit"])
def test_a_nonlinear_fit_recovers_the_truth_eager_and_jitted(transform):
    solve = transform(
        lambda y0: lm_solve(linearize(_exp_residual), y0, Tolerance(), SCHEDULE)
    )
    state, stats = solve(jnp.array([1.0, 0.0]))
    np.testing.assert_allclose(state.y, [2.0, -0.7], atol=1e-10)
    assert int(stats.status) == 1 and 0 < int(stats.num_iters) < 100
    costs = np.asarray(stats.costs)[: int(stats.num_iters) + 1]
    assert np.all(np.diff(costs) <= 0)  # an accepted step never raises the cost
    assert np.isnan(stats.costs[-1])


def test_a_fixed_run_is_vmappable_and_equals_one_problem_at_a_time():
    def fit(scale):
        resid_jac = linearize(lambda y: _exp_residual(y) * scale)
        return lm_run(resid_jac, jnp.array([1.0, 0.0]), 3, SCHEDULE)  # not converged

    scales = jnp.array([0.5, 1.0, 3.0])
    batched = jax.jit(jax.vmap(fit))(scales)
    for i, s in enumerate(scales):
        one = fit(s)
        np.testing.assert_allclose(batched.y[i], one.y, rtol=1e-12)
        np.testing.assert_allclose(batched.cost[i], one.cost, rtol=1e-10, atol=1e-24)
    chex.assert_shape(batched.jac, (3, TIMES.size, 2))


def test_a_failed_model_evaluation_is_rejected_and_never_enters_the_estimate():
    def residual(y):  # the model fails (NaN) beyond y = 0.5, the optimum is at 1
        r = jnp.stack([y[0] - 1.0, 0.1 * y[0]])
        return jnp.where(y[0] > 0.5, jnp.nan, r)

    state = lm_run(linearize(residual), jnp.array([0.0]), 20, SCHEDULE)
    assert np.isfinite(float(state.cost))
    assert 0.0 < float(state.y[0]) <= 0.5
    assert float(state.damping) > SCHEDULE.init  # rejections grew it


def test_the_box_projects_every_step():
    box = (jnp.array([-jnp.inf, -0.5]), jnp.array([1.5, jnp.inf]))
    state = lm_run(linearize(_exp_residual), jnp.array([1.0, 0.0]), 30, SCHEDULE,
                   box=box)  # fmt: skip
    assert float(state.y[0]) == 1.5 and float(state.y[1]) >= -0.5
    np.testing.assert_allclose(state.resid, _exp_residual(state.y))


def test_the_hint_comes_from_the_last_accepted_point():
    def residual(y, hint):  # the hint: the point it was evaluated at
        return _exp_residual(y), y

    resid_jac = linearize(residual, hinted=True)
    state = lm_init(resid_jac, jnp.array([1.0, 0.0]), SCHEDULE, hint=jnp.zeros(2))
    for _ in range(6):
        state, accepted, step_norm = lm_iterate(resid_jac, state, SCHEDULE)
        assert np.isfinite(float(step_norm))
        np.testing.assert_array_equal(state.hint, state.y)


def test_the_damping_rules():
    assert bool(is_accepted(1.0, 1.0)) and not bool(is_accepted(1.1, 1.0))
    assert not bool(is_accepted(jnp.nan, 1.0)) and not bool(is_accepted(jnp.inf, 2.0))
    sched = Damping(init=1e-3, shrink=10.0, grow=4.0, low=1e-6, high=1.0)
    assert float(next_damping(1e-3, True, sched)) == pytest.approx(1e-4)
    assert float(next_damping(1e-3, False, sched)) == pytest.approx(4e-3)
    assert float(next_damping(1e-6, True, sched)) == pytest.approx(1e-6)  # floor
    assert float(next_damping(0.5, False, sched)) == 1.0  # ceiling
    with pytest.raises(ValueError, match="shrink"):
        Damping(shrink=1.0)
    with pytest.raises(ValueError, match="max_iters"):
        Tolerance(max_iters=0)


def test_inverse_psd_floors_or_drops_an_unidentified_direction():
    mat = jnp.diag(jnp.array([4.0, 1.0, 0.0]))
    floored = inverse_psd(mat)
    assert np.all(np.isfinite(floored)) and float(floored[2, 2]) > 1e12
    np.testing.assert_allclose(floored[:2, :2], np.diag([0.25, 1.0]), rtol=1e-12)
    rng = np.random.default_rng(1)
    low_rank = rng.normal(size=(5, 3))
    gram = low_rank @ low_rank.T  # [5, 5] of rank 3
    np.testing.assert_allclose(
        inverse_psd(jnp.asarray(gram), rcond=1e-12),
        np.linalg.pinv(gram, rcond=1e-12),
        rtol=1e-8,
        atol=1e-10,
    )
