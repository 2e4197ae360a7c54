"""Conservation audit of a solved operating point (engine.md check 1).

Recomputes the balances from the station values, independently of the residual vector
the solver drove to zero: whole-engine mass and energy, and the two shaft power
balances. Energy in: air W2 h(T2) + fuel Wf (h_ref + eta_b LHV). Energy out: bypass W18
h(T21), core exhaust W50 h(T50, FAR50), customer bleed h(T30), shaft offtake, and the
mechanical losses (1 - eta_m) of both spools.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.models.turbofan.physics import cycle, thermo
from jaxcal.models.turbofan.physics.design import EngineDesign, design_point


class Audit(NamedTuple):
    mass: jax.Array  # relative imbalance of the whole engine
    energy: jax.Array
    hp_shaft: jax.Array
    lp_shaft: jax.Array


def audit_point(d: EngineDesign, w, theta, effects, z) -> Audit:
    """Relative imbalances at the solution ``z`` of one sample (all ~1e-12 when
    solved)."""
    dp = design_point(d)
    _, st = cycle.balance(d, dp, w, theta, effects, z)
    mass_in = st.w2 + st.wf
    mass_out = st.w_byp + st.w50 + st.w_cust
    far50 = st.wf / (st.w50 - st.wf)
    h_ref = thermo.enthalpy(thermo.T_REF_K * 1.8)
    e_in = st.w2 * thermo.enthalpy(st.t2) + st.wf * (h_ref + d.eta_burner * d.lhv)
    losses = (1.0 - d.eta_mech_hp) * st.power_hpt + (1.0 - d.eta_mech_lp) * st.power_lpt
    e_out = (
        st.w_byp * thermo.enthalpy(st.t21)
        + st.w50 * thermo.enthalpy(st.t50, far50)
        + st.w_cust * thermo.enthalpy(st.t30)
        + st.power_offtake
        + losses
    )
    hp = d.eta_mech_hp * st.power_hpt - st.power_hpc - st.power_offtake
    lp = d.eta_mech_lp * st.power_lpt - st.power_fan - st.power_lpc
    return Audit(
        mass=jnp.abs(mass_in - mass_out) / mass_in,
        energy=jnp.abs(e_in - e_out) / e_in,
        hp_shaft=jnp.abs(hp) / st.power_hpc,
        lp_shaft=jnp.abs(lp) / (st.power_fan + st.power_lpc),
    )
