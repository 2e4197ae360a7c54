"""Variable-specific-heat gas properties for air and kerosene combustion products.

Walsh & Fletcher, *Gas Turbine Performance*, 2nd ed., eq. F3.23-F3.27 (physics_facts.md
2.2): with Tz = T[K]/1000,

    cp_air = sum_{i=0..8} A_i Tz^i,
    cp_gas = cp_air + FAR/(1+FAR) sum_{i=0..7} B_i Tz^i

in kJ/(kg K). Enthalpy h = int cp dT and the entropy function phi = int cp/T dT are
closed form for a polynomial; isentropic steps solve phi(T_s) = phi(T_in) + R ln(PR) and
enthalpy inversions solve h(T) = h_target with a few fixed Newton iterations (both
monotone, so a fixed count is enough: 4 iterations reach 1e-13 relative from the
constant-gamma guess).

Units: the public functions take degR and return BTU/lbm and BTU/(lbm degR); the
polynomial lives in SI and is converted here, in one place. The combustion-products
enthalpy is referenced so that h_gas(T_ref) = h_air(T_ref) at T_ref = 298.15 K: the
fuel's lower heating value is defined at that reference, which makes the burner energy
balance W_air h_air(T3) + Wf (h_ref + eta_b LHV) = (W_air + Wf) h_gas(T4) exact.
"""

from __future__ import annotations

import functools
import inspect

import jax
import jax.numpy as jnp

from jaxcal.models.turbofan.physics.constants import (
    K_PER_R,
    KJ_KG_K_PER_BTU_LBM_R,
    R_AIR_BTU,
)

_A = (0.992313, 0.236688, -1.852148, 6.083152, -8.893933, 7.097112, -3.234725,
      0.794571, -0.081873)  # fmt: skip
_B = (-0.718874, 8.747481, -15.863157, 17.254096, -10.233795, 3.081778, -0.361112,
      -0.003919)  # fmt: skip
T_REF_K = 298.15
_TZ_REF = T_REF_K / 1000.0
# kJ/kg per BTU/lbm is 2.326; kJ/(kg K) per BTU/(lbm R) is 4.1868.
_KJKG_PER_BTULBM = 2.326
NEWTON_ITERATIONS = 4


def _traced_once(fn):
    """``fn`` jitted, so that a trace reuses it: the engine calls these functions
    hundreds of times per balance, and under ``vmap``, ``jvp`` and loops each inline
    call was traced and batched afresh (about half of a turbofan program's trace
    time). A literal ``far`` (0.0 for air) stays a Python number, which skips the
    products polynomial at trace time (:func:`_is_air`); ``unroll`` is static too.
    In float64, F, its Jacobians and the hinted stream keep their bits (XLA inlines
    the calls); ``_poly`` stays inline: jitted on its own it moved F by ulps."""
    signature = inspect.signature(fn)
    names = [n for n in ("far", "unroll") if n in signature.parameters]
    static = jax.jit(fn, static_argnames=names)
    traced_far = jax.jit(fn, static_argnames=[n for n in names if n != "far"])

    @functools.wraps(fn)
    def call(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        far = bound.arguments.get("far", 0.0)
        jitted = static if isinstance(far, (int, float)) else traced_far
        return jitted(**bound.arguments)

    return call


def _poly(coeffs, tz):
    out = jnp.zeros_like(tz) + coeffs[-1]
    for c in coeffs[-2::-1]:
        out = out * tz + c
    return out


def _poly_int(coeffs, tz):
    """sum c_i tz^(i+1)/(i+1): antiderivative of the cp polynomial in tz."""
    return _poly(tuple(c / (i + 1) for i, c in enumerate(coeffs)), tz) * tz


def _poly_int_over_t(coeffs, tz):
    """c_0 ln tz + sum_{i>=1} c_i tz^i / i: antiderivative of cp/T."""
    rest = _poly(tuple(c / (i + 1) for i, c in enumerate(coeffs[1:])), tz) * tz
    return coeffs[0] * jnp.log(tz) + rest


def _tz(t_r):
    return jnp.asarray(t_r) * K_PER_R / 1000.0


def _is_air(far):
    # a literal 0.0 FAR (compressors) skips the products polynomial at trace time
    return isinstance(far, (int, float)) and far == 0.0


def _fuel_weight(far):
    far = jnp.asarray(far)
    return far / (1.0 + far)


@_traced_once
def cp(t_r, far=0.0):
    """Specific heat at constant pressure [BTU/(lbm degR)] at T [degR] and
    fuel-air ratio."""
    tz = _tz(t_r)
    cp_kj = _poly(_A, tz)
    if not _is_air(far):
        cp_kj = cp_kj + _fuel_weight(far) * _poly(_B, tz)
    return cp_kj / KJ_KG_K_PER_BTU_LBM_R


@_traced_once
def enthalpy(t_r, far=0.0):
    """Specific enthalpy [BTU/lbm] (air: from 0 K; products: matched to air
    at 298.15 K)."""
    tz = _tz(t_r)
    h = _poly_int(_A, tz)
    if not _is_air(far):
        h = h + _fuel_weight(far) * (_poly_int(_B, tz) - _poly_int(_B, _TZ_REF))
    return 1000.0 * h / _KJKG_PER_BTULBM


@_traced_once
def entropy_function(t_r, far=0.0):
    """phi(T) = int cp/T dT [BTU/(lbm degR)] (an additive constant is irrelevant)."""
    tz = _tz(t_r)
    phi = _poly_int_over_t(_A, tz)
    if not _is_air(far):
        phi = phi + _fuel_weight(far) * _poly_int_over_t(_B, tz)
    return phi / KJ_KG_K_PER_BTU_LBM_R


def gamma(t_r, far=0.0):
    """Ratio of specific heats cp/(cp - R)."""
    c = cp(t_r, far)
    return c / (c - R_AIR_BTU)


def _iterate(step, t0, unroll: bool):
    """``NEWTON_ITERATIONS`` applications of ``step(i, t)``.

    Rolled (default), a ``fori_loop`` keeps the traced program and compile time small,
    and XLA:CPU differentiates it cheaply (unrolled, the forward-mode Jacobian of the
    balance is ~5x slower: XLA duplicates the primal chain into every tangent fusion).
    Unrolled, a *primal-only* evaluation is ~2x faster under ``vmap`` (no loop
    thunks) and gives the same bits; the balance's callers choose (``unroll``).
    """
    if not unroll:
        return jax.lax.fori_loop(0, NEWTON_ITERATIONS, step, t0)
    t = t0
    for i in range(NEWTON_ITERATIONS):
        t = step(i, t)
    return t


@_traced_once
def temperature_from_enthalpy(h, far, t_guess, unroll: bool = False):
    """Invert h(T, far) = h by fixed Newton iterations from ``t_guess`` [degR]."""

    def step(_, t):
        return t - (enthalpy(t, far) - h) / cp(t, far)

    return _iterate(step, t_guess, unroll)


@_traced_once
def isentropic_temperature(t_in, pr, far, t_guess, unroll: bool = False):
    """T_s with phi(T_s) = phi(T_in) + R ln(PR) (PR = P_out/P_in; < 1 for expansion)."""
    target = entropy_function(t_in, far) + R_AIR_BTU * jnp.log(pr)

    def step(_, t):
        return t - (entropy_function(t, far) - target) * t / cp(t, far)

    return _iterate(step, t_guess, unroll)


@_traced_once
def compress(t_in, pr, eta, far=0.0, unroll: bool = False):
    """Adiabatic compression: exit temperature [degR] and specific work [BTU/lbm].

    h_out = h_in + (h_s(PR) - h_in)/eta (physics_facts.md 2.3).
    """
    g = gamma(t_in, far)
    t_s_guess = t_in * pr ** ((g - 1.0) / g)
    t_s = isentropic_temperature(t_in, pr, far, t_s_guess, unroll)
    h_in = enthalpy(t_in, far)
    dh = (enthalpy(t_s, far) - h_in) / eta
    t_guess = t_in + (t_s_guess - t_in) / eta
    t_out = temperature_from_enthalpy(h_in + dh, far, t_guess, unroll)
    return t_out, dh


@_traced_once
def expand(t_in, pr, eta, far, unroll: bool = False):
    """Adiabatic expansion by PR = P_in/P_out > 1: exit temperature and specific work.

    h_out = h_in - eta (h_in - h_s) (physics_facts.md 2.5).
    """
    g = gamma(t_in, far)
    t_s_guess = t_in * pr ** (-(g - 1.0) / g)
    t_s = isentropic_temperature(t_in, 1.0 / pr, far, t_s_guess, unroll)
    h_in = enthalpy(t_in, far)
    dh = eta * (h_in - enthalpy(t_s, far))
    t_guess = t_in - eta * (t_in - t_s_guess)
    t_out = temperature_from_enthalpy(h_in - dh, far, t_guess, unroll)
    return t_out, dh


def mix(w_a, h_a, w_b, h_b, far_mix, t_guess, unroll: bool = False):
    """Adiabatic mixing of two streams: mixed temperature for the given mixed FAR."""
    h_mix = (w_a * h_a + w_b * h_b) / (w_a + w_b)
    return temperature_from_enthalpy(h_mix, far_mix, t_guess, unroll), h_mix
