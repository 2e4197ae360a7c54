"""Convergent nozzle flow with a smooth choked / unchoked transition
(physics_facts 2.7).

The throat static pressure is a smooth maximum of the ambient pressure and the critical
pressure Pt/PR_cr, so the flow is C-infinity in (Pt, P_amb) and the balance Jacobian has
no kink where the nozzle chokes. Flow per unit area:

    W sqrt(Tt) / (A Pt) = sqrt(gamma g_c / R) M
                          (1 + (gamma-1)/2 M^2)^(-(gamma+1)/(2(gamma-1)))

with M from Pt/Ps. A is in in^2, Pt in psia, Tt in degR, W in lbm/s.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.models.turbofan.physics.constants import FT_LBF_PER_BTU, GC, R_AIR_BTU

R_FT_LBF = R_AIR_BTU * FT_LBF_PER_BTU  # ft lbf / (lbm degR)
# Width of the smooth max, relative to the critical pressure: the flow error it causes
# is below 1e-4 away from the choke point and zero in the fit (areas absorb it).
SMOOTH_MAX_WIDTH = 0.02


def _smooth_max(a, b, width):
    return 0.5 * (a + b + jnp.sqrt((a - b) ** 2 + width**2))


_M2_LINEAR = 1e-3  # below this M^2, M is continued linearly (also to negative values)


def _mach_from_m2(m2):
    """sqrt(M^2), continued as the C1 tangent line below M^2 = 1e-3 (M = 0.032).

    An iterate of the Newton solve may have Pt < P_amb; a floored or NaN Mach there
    would leave the balance with a flat or undefined Jacobian. The continuation gives a
    small *negative* flow instead, so the iteration is pushed back; normal operation
    never reaches it.
    """
    eps = _M2_LINEAR
    safe = jnp.maximum(m2, eps)
    return jnp.where(
        m2 > eps, jnp.sqrt(safe), 0.5 * (m2 / jnp.sqrt(eps) + jnp.sqrt(eps))
    )


def nozzle_flow(pt, tt, p_amb, area_in2, gamma, cd=1.0):
    """Mass flow [lbm/s] through a convergent nozzle and its throat Mach number.

    Args:
        pt, tt: inlet total pressure [psia] and temperature [degR].
        p_amb: ambient static pressure [psia].
        area_in2: geometric throat area [in^2].
        gamma: ratio of specific heats at the nozzle inlet.
        cd: discharge coefficient.

    Returns:
        (W [lbm/s], M_throat).
    """
    g = gamma
    pr_crit = ((g + 1.0) / 2.0) ** (g / (g - 1.0))
    p_crit = pt / pr_crit
    ps = _smooth_max(p_amb, p_crit, SMOOTH_MAX_WIDTH * p_crit)
    # Pt/Ps may dip below 1 during the iteration: log form keeps the power defined
    m2_raw = 2.0 / (g - 1.0) * jnp.expm1((g - 1.0) / g * jnp.log(pt / ps))
    mach = _mach_from_m2(m2_raw)
    m2 = mach**2
    flow_fn = (
        jnp.sqrt(g * GC / R_FT_LBF)
        * mach
        * (1.0 + 0.5 * (g - 1.0) * m2) ** (-(g + 1.0) / (2.0 * (g - 1.0)))
    )
    return cd * area_in2 * pt / jnp.sqrt(tt) * flow_fn, mach
