"""The Newton solve's implicit derivatives, outputs included, on a balance with a
closed-form solution: z^3 + z = p has dz/dp = 1 / (3 z^2 + 1)."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.models.turbofan.physics import solver


def _balance(z, params):
    p, q = params
    r = z**3 + z - p  # one unknown per parameter row
    y = jnp.stack([jnp.sin(z[0]) * q, z[1] ** 2 + q])  # outputs read z and q
    return r, y, (jnp.all(z > -10.0),)


def _outputs(params):
    z, y, (ok,), info = solver.solve_closed(_balance, jnp.zeros(2), params)
    return z, y, ok, info


def test_the_outputs_tangent_is_the_implicit_derivative_forward_and_reverse():
    p, q = jnp.array([2.0, 10.0]), jnp.array(0.7)
    z, y, ok, info = jax.jit(_outputs)((p, q))
    assert bool(ok) and float(info.residual_norm) < 1e-11
    np.testing.assert_allclose(z**3 + z, p, rtol=1e-12)
    dz_dp = 1.0 / (3.0 * z**2 + 1.0)
    want = np.array([
        [np.cos(z[0]) * q * dz_dp[0], 0.0, np.sin(z[0])],
        [0.0, 2.0 * z[1] * dz_dp[1], 1.0],
    ])  # fmt: skip

    def flat(v):
        return _outputs((v[:2], v[2]))[1]

    v = jnp.array([2.0, 10.0, 0.7])
    np.testing.assert_allclose(jax.jacfwd(flat)(v), want, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(jax.jacrev(flat)(v), want, rtol=1e-12, atol=1e-14)
    # the solution's own tangent, as solve() gives it
    jz = jax.jacfwd(lambda pp: solver.solve(lambda zz, a: zz**3 + zz - a,
                                            jnp.zeros(2), pp)[0])(p)  # fmt: skip
    np.testing.assert_allclose(jz, np.diag(dz_dp), rtol=1e-12)


def test_a_derivative_differentiates_again_in_every_order():
    """A Hessian through the solve, reverse over forward as well (the loop's Jacobians
    carry their own implicit tangent): y0 = q sin(z0) with z0^3 + z0 = p0."""
    p, q = 2.0, 0.7

    def y0(v):
        return _outputs((jnp.array([v[0], 10.0]), v[1]))[1][0]

    z = float(_outputs((jnp.array([p, 10.0]), jnp.array(q)))[0][0])
    z1 = 1.0 / (3.0 * z**2 + 1.0)  # dz/dp
    z2 = -6.0 * z * z1**3  # d2z/dp2
    want = np.array([
        [q * (-np.sin(z) * z1**2 + np.cos(z) * z2), np.cos(z) * z1],
        [np.cos(z) * z1, 0.0],
    ])  # fmt: skip
    v = jnp.array([p, q])
    for hess in (jax.hessian, lambda f: jax.jacrev(jax.jacfwd(f)),
                 lambda f: jax.jacfwd(jax.jacfwd(f))):  # fmt: skip
        got = hess(y0)(v)
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-13)
