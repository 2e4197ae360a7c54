"""The unrolled solve of small positive definite systems equals LAPACK's, in value
and gradient, and leaves no LAPACK call in the program (why it exists)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.numerics.small_solve import UNROLL_MAX, spd_solve


@pytest.mark.parametrize("n", [1, 2, 4, UNROLL_MAX, UNROLL_MAX + 3])
def test_spd_solve_matches_lapack(n):
    rng = np.random.default_rng(n)
    m = rng.normal(size=(n, n))
    a = (m @ m.T + 0.1 * np.eye(n)).astype(np.float32)
    b = rng.normal(size=(n, 3)).astype(np.float32)
    want = np.linalg.solve(a.astype(np.float64), b.astype(np.float64))
    got = np.asarray(jax.jit(spd_solve)(a, b))
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-4 * np.abs(want).max())
    vec = np.asarray(spd_solve(jnp.asarray(a), jnp.asarray(b[:, 0])))
    assert vec.shape == (n,)
    np.testing.assert_allclose(vec, got[:, 0], rtol=1e-5, atol=1e-6)


def test_spd_solve_gradient_and_program():
    a = jnp.array([[4.0, 1.0], [1.0, 3.0]])
    b = jnp.array([1.0, 2.0])
    grad = jax.grad(lambda a_: spd_solve(a_, b).sum())(a)
    want = jax.grad(lambda a_: jnp.linalg.solve(a_, b).sum())(a)
    np.testing.assert_allclose(grad, want, rtol=1e-5)
    text = jax.jit(spd_solve).lower(a, b).compile().as_text()
    assert "custom-call" not in text and " while(" not in text


def test_spd_solve_refuses_wrong_shapes():
    with pytest.raises(ValueError, match="square"):
        spd_solve(jnp.ones((2, 3)), jnp.ones(2))
