"""Variable-cp gas properties: consistency of cp, h, phi and the inversions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.models.turbofan.physics import thermo


@pytest.mark.parametrize(
    "t_k,cp_ref", [(300.0, 1.0039), (1000.0, 1.1412), (1500.0, 1.2109)]
)
def test_air_cp_matches_ideal_gas_tables(t_k, cp_ref):
    # physics_facts.md 2.2 spot checks, kJ/(kg K)
    cp_si = float(thermo.cp(t_k * 1.8)) * 4.1868
    assert cp_si == pytest.approx(cp_ref, rel=5e-3)


@pytest.mark.parametrize("far", [0.0, 0.025])
def test_cp_is_the_derivative_of_enthalpy_and_entropy_function(far):
    t = jnp.array([600.0, 1500.0, 3000.0])
    dh = jax.vmap(jax.grad(lambda tt: thermo.enthalpy(tt, far)))(t)
    dphi = jax.vmap(jax.grad(lambda tt: thermo.entropy_function(tt, far)))(t)
    np.testing.assert_allclose(dh, thermo.cp(t, far), rtol=1e-12)
    np.testing.assert_allclose(dphi * t, thermo.cp(t, far), rtol=1e-12)


def test_inversions_are_exact():
    t = jnp.array([500.0, 1200.0, 3200.0])
    far = 0.02
    back = thermo.temperature_from_enthalpy(thermo.enthalpy(t, far), far, t * 0.9)
    np.testing.assert_allclose(back, t, rtol=1e-12)
    t_c = jnp.array([500.0, 700.0, 900.0])  # compressor inlets, constant-gamma guess
    t_s = thermo.isentropic_temperature(t_c, 10.0, far, t_c * 10.0 ** (0.4 / 1.4))
    gain = thermo.entropy_function(t_s, far) - thermo.entropy_function(t_c, far)
    np.testing.assert_allclose(gain, thermo.R_AIR_BTU * np.log(10.0), rtol=1e-12)


def test_compression_and_expansion_work_balance():
    t_out, dh = thermo.compress(518.67, 20.0, 0.85)
    assert float(thermo.enthalpy(t_out) - thermo.enthalpy(518.67)) == pytest.approx(
        float(dh)
    )
    # an ideal compressor followed by an ideal turbine over the same PR returns to T_in
    t_c, _ = thermo.compress(518.67, 20.0, 1.0)
    t_e, _ = thermo.expand(t_c, 20.0, 1.0, 0.0)
    assert float(t_e) == pytest.approx(518.67, rel=1e-10)


def test_jitted_properties_keep_the_engines_bits(monkeypatch, cmapss):
    # the properties are nested jits (so that a trace reuses them); the engine's F
    # must be the inline functions' to the bit, F's bits being the paper's (jitting
    # ``_poly`` as well moved F by ~2e-14 relative, which this catches)
    w = np.array([[10000.0, 0.4, 80.0, 540.0], [30000.0, 0.8, 95.0, 480.0]])
    theta = np.full((2, 10), -0.004)

    def run():
        return np.asarray(
            jax.jit(jax.vmap(lambda w, th: cmapss.evaluate(w, th)[0]))(w, theta)
        )

    jitted = run()
    for name in ("cp", "enthalpy", "entropy_function", "temperature_from_enthalpy",
                 "isentropic_temperature", "compress", "expand"):  # fmt: skip
        monkeypatch.setattr(thermo, name, getattr(thermo, name).__wrapped__)
    inline = run()
    np.testing.assert_array_equal(jitted, inline)
