"""The analytic calibration problem: shapes, padding, drift, closed-form answer."""

import jax
import numpy as np
from support.analytic import analytic_dynamics, make_analytic_problem


def test_problem_is_consistent_and_invertible():
    # Same jit signature as the runner tests, so the compiled generator is shared.
    problem = jax.jit(
        make_analytic_problem, static_argnames=("num_units", "num_steps", "min_length")
    )(jax.random.key(0), num_units=3, num_steps=24, min_length=12)
    lengths = np.asarray(problem.lengths)
    assert problem.w.shape == (3, 24, 2) and problem.x.shape == (3, 24, 4)
    assert problem.theta.shape == (3, 24, 1)
    assert np.all((lengths >= 12) & (lengths <= 24)) and np.any(lengths < 24)
    valid = np.arange(24)[None] < lengths[:, None]
    theta = np.asarray(problem.theta)
    assert np.all((theta[valid] >= 0.1) & (theta[valid] <= 0.9))
    # Slow monotone drift; zero padding after each unit's length.
    assert np.all(np.diff(theta, axis=1)[valid[:, 1:]] >= 0)
    assert np.all(np.asarray(problem.x)[~valid] == 0)
    # x = A w + B theta + c, so theta = B^+ (x - A w - c) on valid rows.
    p = problem.dyn_params
    residual = np.asarray(problem.x) - np.asarray(problem.w) @ np.asarray(p.a).T
    recovered = (residual - np.asarray(p.c)) @ np.linalg.pinv(np.asarray(p.b)).T
    np.testing.assert_allclose(recovered[valid], theta[valid], atol=1e-8)
    x0 = analytic_dynamics(p, problem.w[0, 0], problem.x[0, 0], problem.theta[0, 0])
    np.testing.assert_allclose(x0, problem.x[0, 0], atol=1e-12)
