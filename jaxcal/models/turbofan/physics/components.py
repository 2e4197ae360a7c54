"""Gas-path component steps shared by the design-point and the off-design cycle.

Each step is a pure function of station quantities (English units: degR, psia, lbm/s,
BTU/lbm) and returns the exit station. Cooling flows follow pyCycle / T-MATS
(physics_facts.md 2.5): flow entering ahead of the rotor is mixed in first and does
work, flow entering at the exit is mixed after the expansion; mixing is an enthalpy
balance.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxcal.models.turbofan.physics import thermo


class Burner(NamedTuple):
    t4: jnp.ndarray  # exit total temperature [degR]
    far: jnp.ndarray  # fuel-air ratio Wf / W3b
    w4: jnp.ndarray  # exit flow W3b + Wf [lbm/s]


def burner_exit(w3b, t30, wf, eta_b, lhv, unroll: bool = False):
    """Burner energy balance (physics_facts.md 2.4) with variable-cp products.

    W3b h_air(T30) + Wf (h_ref + eta_b LHV) = (W3b + Wf) h_gas(T4, FAR), FAR = Wf/W3b.
    """
    far = wf / w3b
    h_ref = thermo.enthalpy(thermo.T_REF_K * 1.8, 0.0)
    h4 = (w3b * thermo.enthalpy(t30, 0.0) + wf * (h_ref + eta_b * lhv)) / (w3b + wf)
    # secant-quality guess: temperature rise at a mean cp of about 0.29 BTU/(lbm R)
    t_guess = t30 + (h4 - thermo.enthalpy(t30, 0.0)) / 0.29
    t4 = thermo.temperature_from_enthalpy(h4, far, t_guess, unroll)
    return Burner(t4=t4, far=far, w4=w3b + wf)


def burner_far_for_t4(t30, t4, eta_b, lhv):
    """FAR that gives exit temperature T4 (design mode), closed form of the same
    balance.

    With h_gas(T, f) = h_air(T) + f/(1+f) H_b(T):
    FAR = (h_air(T4) - h_air(T30)) / (h_ref + eta_b LHV - h_air(T4) - H_b(T4)).
    """
    h_ref = thermo.enthalpy(thermo.T_REF_K * 1.8, 0.0)
    h_air4 = thermo.enthalpy(t4, 0.0)
    # H_b(T4) = d/df [(1+f) h_gas] at fixed T: evaluate via two FARs (exactly linear)
    h_b = (2.0 * thermo.enthalpy(t4, 1.0) - h_air4) - h_air4
    return (h_air4 - thermo.enthalpy(t30, 0.0)) / (h_ref + eta_b * lhv - h_air4 - h_b)


class TurbineExit(NamedTuple):
    t_rotor_in: jnp.ndarray  # rotor inlet after the ahead-of-rotor cooling mix [degR]
    t_out: jnp.ndarray  # exit after the exit cooling mix [degR]
    w_rotor: jnp.ndarray  # flow through the rotor [lbm/s]
    w_out: jnp.ndarray  # exit flow including all cooling [lbm/s]
    far_rotor: jnp.ndarray
    far_out: jnp.ndarray
    power: jnp.ndarray  # shaft power [BTU/s]
    dh: jnp.ndarray  # rotor specific work [BTU/lbm]


def mix_cooling(w, t, far, w_cool, h_cool, unroll: bool = False):
    """Mix cooling air (FAR 0, enthalpy h_cool) into a gas stream.

    Returns:
        (w_mix, far_mix, h_mix, t_mix).
    """
    fuel = w * far / (1.0 + far)
    w_mix = w + w_cool
    far_mix = fuel / (w_mix - fuel)
    h_mix = (w * thermo.enthalpy(t, far) + w_cool * h_cool) / w_mix
    t_mix = thermo.temperature_from_enthalpy(h_mix, far_mix, t, unroll)
    return w_mix, far_mix, h_mix, t_mix


def turbine_rotor(w_r, t_r, far_r, pr, eta, w_cool_exit, h_cool, unroll: bool = False):
    """Expansion through the rotor by PR = Pt_in/Pt_out, then the exit cooling mix.

    Args:
        w_r, t_r, far_r: rotor inlet flow, temperature and FAR (after
            :func:`mix_cooling` of the ahead-of-rotor cooling air).
        pr, eta: pressure ratio and isentropic efficiency.
        w_cool_exit, h_cool: cooling air mixed at the exit and its enthalpy.
        unroll: unrolled thermo inversions
            (:func:`jaxcal.models.turbofan.physics.thermo._iterate`).
    """
    t_exp, dh = thermo.expand(t_r, pr, eta, far_r, unroll)
    w_o, far_o, _, t_o = mix_cooling(w_r, t_exp, far_r, w_cool_exit, h_cool, unroll)
    return TurbineExit(t_r, t_o, w_r, w_o, far_r, far_o, w_r * dh, dh)


def turbine_pr_for_work(w_r, t_r, far_r, h_r, power, eta):
    """Pressure ratio that delivers ``power`` [BTU/s] (design mode, closed form).

    h_out = h_in - dh, h_s = h_in - dh/eta, PR = exp((phi(T_in) - phi(T_s))/R).
    """
    dh = power / w_r
    t_s = thermo.temperature_from_enthalpy(h_r - dh / eta, far_r, t_r - dh / eta / 0.3)
    phi_drop = thermo.entropy_function(t_r, far_r) - thermo.entropy_function(t_s, far_r)
    return jnp.exp(phi_drop / thermo.R_AIR_BTU)
