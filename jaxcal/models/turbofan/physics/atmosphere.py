"""ISA atmosphere, ram and inlet conditions (physics_facts.md section 2.1).

All functions are pure ``jax.numpy`` and broadcast over any batch shape. Altitude in ft,
temperatures in degR, pressures in psia. An off-standard day is carried by T2: the
ambient static temperature is backed out of the ram relation, the ambient pressure stays
ISA.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.models.turbofan.physics.constants import P_STD_PSIA, T_STD_R

TROPOPAUSE_FT = 36089.0
LAPSE_R_PER_FT = 0.0035662
T_STRATOSPHERE_R = 389.97
P_TROPOPAUSE_PSIA = 3.2825
STRATO_SCALE_FT = 20806.0
GAMMA_AIR = 1.4


def isa_static(alt_ft):
    """ISA static temperature [degR] and pressure [psia] at altitude.

    Troposphere: T = 518.67 - 0.0035662 h, P = 14.696 (T/518.67)^5.2559; lower
    stratosphere (h > 36,089 ft): T = 389.97, P = 3.2825 exp(-(h - 36,089)/20,806)
    (physics_facts.md 2.1). A smooth blend over +-200 ft keeps derivatives continuous.

    Args:
        alt_ft: altitude [ft], any shape.

    Returns:
        (T_amb [degR], P_amb [psia]) with the shape of ``alt_ft``.
    """
    alt = jnp.asarray(alt_ft)
    t_tropo = T_STD_R - LAPSE_R_PER_FT * alt
    p_tropo = P_STD_PSIA * (jnp.maximum(t_tropo, 1.0) / T_STD_R) ** 5.2559
    p_strato = P_TROPOPAUSE_PSIA * jnp.exp(-(alt - TROPOPAUSE_FT) / STRATO_SCALE_FT)
    # logistic blend: exact to 1e-9 relative 2,000 ft away from the tropopause
    s = 1.0 / (1.0 + jnp.exp(-(alt - TROPOPAUSE_FT) / 100.0))
    t_amb = (1.0 - s) * t_tropo + s * T_STRATOSPHERE_R
    p_amb = jnp.exp((1.0 - s) * jnp.log(p_tropo) + s * jnp.log(p_strato))
    return t_amb, p_amb


def ram_ratio(mach):
    """Total-to-static temperature ratio 1 + (gamma-1)/2 M^2 with gamma = 1.4."""
    return 1.0 + 0.5 * (GAMMA_AIR - 1.0) * jnp.asarray(mach) ** 2


def isa_total_temperature(alt_ft, mach, delta_t_r=0.0):
    """Fan-face total temperature T2 [degR] for an ISA (+ delta_t_r) day.

    T2 = (T_ISA(alt) + dT) (1 + 0.2 M^2): the inlet is adiabatic, so T2 = Tt0
    (C-MAPSS s1 equals this to 0.01 degR, data_facts.md 1.3).
    """
    t_amb, _ = isa_static(alt_ft)
    return (t_amb + delta_t_r) * ram_ratio(mach)


def free_stream(alt_ft, mach, t2_r):
    """Ambient static and free-stream total conditions.

    Args:
        alt_ft, mach, t2_r: operating condition (any broadcastable shapes).

    Returns:
        (T_amb, P_amb, Pt0): ambient static temperature [degR] implied by T2, ISA static
        pressure [psia] and free-stream total pressure [psia].
    """
    _, p_amb = isa_static(alt_ft)
    rr = ram_ratio(mach)
    t_amb = jnp.asarray(t2_r) / rr
    pt0 = p_amb * rr ** (GAMMA_AIR / (GAMMA_AIR - 1.0))
    return t_amb, p_amb, pt0
