"""The thermal example's closed-form step equals the exact matrix exponential."""

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from jaxcal.models import thermal


def test_closed_form_exponential_matches_expm_across_the_parameter_box():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        lo = np.array([p[1] for p in thermal.PARAMETERS.values()])
        hi = np.array([p[2] for p in thermal.PARAMETERS.values()])
        for theta in rng.uniform(lo, hi, (20, 4)):
            a = thermal._system_matrix(jnp.asarray(theta)) * thermal.DT
            np.testing.assert_allclose(
                np.asarray(thermal._expm2(a)), np.asarray(jsl.expm(a)),
                rtol=1e-10, atol=1e-13,
            )  # fmt: skip


def test_step_relaxes_to_the_steady_state():
    with jax.enable_x64(True):
        model = thermal.thermal_model()
        w = jnp.array([1500.0, 290.0])
        theta = jnp.asarray(model.nominal)
        z = jnp.array([300.0, 295.0])
        for _ in range(3000):  # slowest mode ~125 samples
            z, x = thermal.thermal_step(z, w, theta)
        np.testing.assert_allclose(
            np.asarray(z), np.asarray(thermal.steady_state(w, theta)), rtol=1e-9
        )
        q = (z[1] - w[1]) / theta[0]
        np.testing.assert_allclose(float(x[2]), float(q), rtol=1e-12)
        np.testing.assert_allclose(float(q), 1500.0, rtol=1e-6)  # heat in = heat out


def test_closed_form_is_stable_for_stiff_and_complex_matrices():
    """Far outside the box the fit may try (a resistance near zero: one mode 1e4
    times faster than the other; a negative capacity: complex eigenvalues), the
    closed form stays finite and equal to expm, and so do its derivatives."""
    with jax.enable_x64(True):
        cases = [
            jnp.array([[-0.03, 0.03], [0.12, -5000.0]]),  # stiff
            jnp.array([[-0.5, 2.0], [-1.0, -0.4]]),  # complex pair
            jnp.array([[-0.2, 0.0], [0.0, -0.2]]),  # repeated eigenvalue (d = 0)
        ]
        for a in cases:
            np.testing.assert_allclose(
                np.asarray(thermal._expm2(a)), np.asarray(jsl.expm(a)),
                rtol=1e-9, atol=1e-12,
            )  # fmt: skip
            jac = jax.jacfwd(thermal._expm2)(a)
            ref = jax.jacfwd(jsl.expm)(a)
            assert np.all(np.isfinite(np.asarray(jac)))
            np.testing.assert_allclose(
                np.asarray(jac), np.asarray(ref), rtol=1e-6, atol=1e-9
            )
