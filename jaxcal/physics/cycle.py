"""Off-design balance of the two-spool separate-flow turbofan (physics_facts.md 4).

Nine unknowns z, all dimensionless and 0 at the design point:

    z0 ln(W2c/W2c_d)   z1 ln(BPR/BPR_d)   z2..z4 beta - beta_d (fan, LPC, HPC)
    z5 ln((PR_HPT-1)/(PR_HPT_d-1))   z6 same for the LPT   z7 ln(NcR_HPC/NcR_HPC_d)
    z8 ln(Wf_corr/Wf_corr_d)

Nine residuals, each normalised by its design value: fan, LPC and HPC flow compatibility,
HPT and LPT flow capacity, core and bypass nozzle flow, HP and LP shaft power balance.
The closure is C-MAPSS-like: the physical fan speed is set by the corrected-speed demand
of the TRA schedule, Nf = NRf_dmd sqrt(T2/518.67), and the fuel flow is solved.

``effects`` extends the model with the parametric effects the closing-the-loop library
needs (see :data:`EFFECT_NAMES`); all zero reproduces the plain engine.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxcal.physics import components, maps, thermo
from jaxcal.physics.atmosphere import free_stream
from jaxcal.physics.constants import HP_PER_BTU_S, P_STD_PSIA, T_STD_R
from jaxcal.physics.design import (
    DesignPoint,
    EngineDesign,
    corrected_fan_speed_demand,
    inlet_recovery,
)
from jaxcal.physics.nozzle import nozzle_flow

NUM_UNKNOWNS = 9
UNKNOWN_NAMES = (
    "ln_w2c", "ln_bpr", "beta_fan", "beta_lpc", "beta_hpc", "ln_pr_hpt", "ln_pr_lpt",
    "ln_ncr_hpc", "ln_wf_corr",
)  # fmt: skip
RESIDUAL_NAMES = (
    "fan_flow", "lpc_flow", "hpc_flow", "hpt_capacity", "lpt_capacity", "core_nozzle",
    "bypass_nozzle", "hp_power", "lp_power",
)  # fmt: skip

# Parametric effects an engine may show that the 10 health modifiers do not declare.
EFFECT_NAMES = (
    "t2_offset",  # degR: the engine inlet is hotter than the T2 reading says
    "customer_bleed",  # fraction of W25 taken overboard at the HPC exit
    "power_offtake",  # hp taken from the HP shaft on top of the design offtake
    "core_nozzle_area",  # relative change of A8
    "bypass_nozzle_area",  # relative change of A18
    "inlet_recovery",  # change of P2/Pt0 (absolute, e.g. -0.005)
)
NUM_EFFECTS = len(EFFECT_NAMES)


class Stations(NamedTuple):
    """Everything the sensors and the conservation audit need (per sample)."""

    t2: jnp.ndarray
    p2: jnp.ndarray
    p_amb: jnp.ndarray
    t21: jnp.ndarray
    p21: jnp.ndarray
    t24: jnp.ndarray
    p24: jnp.ndarray
    t25: jnp.ndarray
    p25: jnp.ndarray
    t30: jnp.ndarray
    p30: jnp.ndarray
    t4: jnp.ndarray
    p40: jnp.ndarray
    t41: jnp.ndarray
    t48: jnp.ndarray
    p45: jnp.ndarray
    t50: jnp.ndarray
    p50: jnp.ndarray
    p15: jnp.ndarray
    nf: jnp.ndarray
    nc: jnp.ndarray
    nf_dmd: jnp.ndarray
    pcn_dmd: jnp.ndarray
    wf: jnp.ndarray
    far: jnp.ndarray
    w2: jnp.ndarray
    w_core: jnp.ndarray
    w_byp: jnp.ndarray
    w31: jnp.ndarray
    w32: jnp.ndarray
    w_cust: jnp.ndarray
    w48: jnp.ndarray
    w50: jnp.ndarray
    w8_noz: jnp.ndarray
    w18_noz: jnp.ndarray
    power_fan: jnp.ndarray
    power_lpc: jnp.ndarray
    power_hpc: jnp.ndarray
    power_hpt: jnp.ndarray
    power_lpt: jnp.ndarray
    power_offtake: jnp.ndarray
    sm_fan: jnp.ndarray
    sm_lpc: jnp.ndarray
    sm_hpc: jnp.ndarray
    h_bleed32: jnp.ndarray


def unpack_theta(theta):
    """Split the 10 N-CMAPSS health modifiers into (eff, flow) per component."""
    return {
        "fan": (theta[0], theta[1]),
        "lpc": (theta[2], theta[3]),
        "hpc": (theta[4], theta[5]),
        "hpt": (theta[6], theta[7]),
        "lpt": (theta[8], theta[9]),
    }


def balance(d: EngineDesign, dp: DesignPoint, w, theta, effects, z, unroll=False):
    """Residuals and stations of the off-design balance for one sample.

    Args:
        d: design constants; dp: their design point (map scalars).
        w: [4] (alt ft, Mach, TRA %, T2 degR).
        theta: [10] health modifiers (N-CMAPSS order).
        effects: [NUM_EFFECTS] extension parameters (zeros = plain model).
        z: [9] unknowns (module docstring).
        unroll: unroll the thermo inversions (static): the same bits, faster when
            the balance is evaluated but not differentiated
            (:func:`jaxcal.physics.thermo._iterate`).

    Returns:
        (residuals [9], Stations).
    """
    alt, mach, tra, t2_meas = w[0], w[1], w[2], w[3]
    h = unpack_theta(theta)
    mode = d.health_mode
    t2 = t2_meas + effects[0]
    _, p_amb, pt0 = free_stream(alt, mach, t2)
    p2 = (inlet_recovery(d, mach) + effects[5]) * pt0
    theta2, delta2 = t2 / T_STD_R, p2 / P_STD_PSIA
    # controller: corrected demand on the *measured* T2
    pcn, nrf_dmd = corrected_fan_speed_demand(d, tra)
    nf = nrf_dmd * jnp.sqrt(t2_meas / T_STD_R)
    # fan
    n_fan = nf / jnp.sqrt(theta2) / dp.nrf
    beta_fan = maps.BETA_DESIGN + z[2]
    wc_fan, pr_fan, eta_fan = maps.compressor_map(
        d.fan, dp.wc_fan, d.pr_fan_d, d.eta_fan_d, n_fan, beta_fan
    )
    wc_fan = wc_fan * (1.0 + h["fan"][1])
    eta_fan = maps.apply_efficiency_modifier(eta_fan, h["fan"][0], mode)
    w2c = dp.wc_fan * jnp.exp(z[0])
    w2 = w2c * delta2 / jnp.sqrt(theta2)
    bpr = d.bpr_d * jnp.exp(z[1])
    w_core = w2 / (1.0 + bpr)
    w_byp = w2 - w_core
    t21, dh_fan = thermo.compress(t2, pr_fan, eta_fan, unroll=unroll)
    p21 = p2 * pr_fan
    # LPC (booster) on the LP shaft
    p21c = p21 * (1.0 - d.dp_fan_duct)
    n_lpc = nf * d.gear_ratio / jnp.sqrt(t21 / T_STD_R) / dp.nc_lpc
    beta_lpc = maps.BETA_DESIGN + z[3]
    wc_lpc, pr_lpc, eta_lpc = maps.compressor_map(
        d.lpc, dp.wc_lpc, d.pr_lpc_d, d.eta_lpc_d, n_lpc, beta_lpc
    )
    wc_lpc = wc_lpc * (1.0 + h["lpc"][1])
    eta_lpc = maps.apply_efficiency_modifier(eta_lpc, h["lpc"][0], mode)
    w21c = w_core * jnp.sqrt(t21 / T_STD_R) / (p21c / P_STD_PSIA)
    t24, dh_lpc = thermo.compress(t21, pr_lpc, eta_lpc, unroll=unroll)
    p24 = p21c * pr_lpc
    # HPC
    t25, p25 = t24, p24 * (1.0 - d.dp_lpc_duct)
    n_hpc = jnp.exp(z[7])
    nc = n_hpc * dp.nc_hpc * jnp.sqrt(t25 / T_STD_R)
    beta_hpc = maps.BETA_DESIGN + z[4]
    wc_hpc, pr_hpc, eta_hpc = maps.compressor_map(
        d.hpc, dp.wc_hpc, d.pr_hpc_d, d.eta_hpc_d, n_hpc, beta_hpc
    )
    wc_hpc = wc_hpc * (1.0 + h["hpc"][1])
    eta_hpc = maps.apply_efficiency_modifier(eta_hpc, h["hpc"][0], mode)
    w25c = w_core * jnp.sqrt(t25 / T_STD_R) / (p25 / P_STD_PSIA)
    t30, dh_hpc = thermo.compress(t25, pr_hpc, eta_hpc, unroll=unroll)
    p30 = p25 * pr_hpc
    w31, w32 = d.bleed_hpt * w_core, d.bleed_lpt * w_core
    w_cust = effects[1] * w_core
    w3b = w_core - w31 - w32 - w_cust
    power_hpc = w_core * dh_hpc - w32 * (1.0 - d.lpt_bleed_work) * dh_hpc
    h30 = thermo.enthalpy(t30)
    h32 = thermo.enthalpy(t25) + d.lpt_bleed_work * dh_hpc
    # burner
    wf = dp.wf_corr * jnp.exp(z[8]) * delta2 * jnp.sqrt(theta2)
    burner = components.burner_exit(w3b, t30, wf, d.eta_burner, d.lhv, unroll)
    p40 = p30 * (1.0 - d.dp_burner)
    # HPT
    pr_hpt = 1.0 + (dp.pr_hpt - 1.0) * jnp.exp(z[5])
    w31r = d.hpt_cool_rotor_frac * w31
    w41, far41, _, t41 = components.mix_cooling(
        burner.w4, burner.t4, burner.far, w31r, h30, unroll
    )
    eta_hpt = maps.turbine_efficiency(
        d.hpt, d.eta_hpt_d, nc / jnp.sqrt(t41) / dp.ntc_hpt
    )
    eta_hpt = maps.apply_efficiency_modifier(eta_hpt, h["hpt"][0], mode)
    hpt = components.turbine_rotor(
        w41, t41, far41, pr_hpt, eta_hpt, w31 - w31r, h30, unroll
    )
    phi_hpt_map = maps.turbine_capacity(d.hpt, dp.phi_hpt, dp.pr_hpt, pr_hpt)
    phi_hpt_map = phi_hpt_map * (1.0 + h["hpt"][1])
    p45 = p40 / pr_hpt
    # LPT
    p45l = p45 * (1.0 - d.dp_hpt_duct)
    pr_lpt = 1.0 + (dp.pr_lpt - 1.0) * jnp.exp(z[6])
    w32r = d.lpt_cool_rotor_frac * w32
    n_lp = nf * d.gear_ratio
    w46, far46, _, t46 = components.mix_cooling(
        hpt.w_out, hpt.t_out, hpt.far_out, w32r, h32, unroll
    )
    eta_lpt = maps.turbine_efficiency(
        d.lpt, d.eta_lpt_d, n_lp / jnp.sqrt(t46) / dp.ntc_lpt
    )
    eta_lpt = maps.apply_efficiency_modifier(eta_lpt, h["lpt"][0], mode)
    lpt = components.turbine_rotor(
        w46, t46, far46, pr_lpt, eta_lpt, w32 - w32r, h32, unroll
    )
    phi_lpt_map = maps.turbine_capacity(d.lpt, dp.phi_lpt, dp.pr_lpt, pr_lpt)
    phi_lpt_map = phi_lpt_map * (1.0 + h["lpt"][1])
    p50 = p45l / pr_lpt
    # nozzles
    p8 = p50 * (1.0 - d.dp_lpt_duct)
    a8 = dp.a8 * (1.0 + effects[3])
    w8_noz, _ = nozzle_flow(
        p8, lpt.t_out, p_amb, a8, thermo.gamma(lpt.t_out, lpt.far_out), d.cd_core
    )
    p15 = p21 * (1.0 - d.dp_bypass)
    a18 = dp.a18 * (1.0 + d.vafn_slope * (d.mach_d - mach)) * (1.0 + effects[4])
    w18_noz, _ = nozzle_flow(p15, t21, p_amb, a18, thermo.gamma(t21), d.cd_bypass)
    # shafts
    offtake = (d.hpx_hp + effects[2]) / HP_PER_BTU_S
    power_fan, power_lpc = w2 * dh_fan, w_core * dh_lpc
    residuals = jnp.stack(
        [
            (w2c - wc_fan) / dp.wc_fan,
            (w21c - wc_lpc) / dp.wc_lpc,
            (w25c - wc_hpc) / dp.wc_hpc,
            (burner.w4 * jnp.sqrt(burner.t4) / p40 - phi_hpt_map) / dp.phi_hpt,
            (hpt.w_out * jnp.sqrt(hpt.t_out) / p45l - phi_lpt_map) / dp.phi_lpt,
            (lpt.w_out - w8_noz) / dp.w8,
            (w_byp - w18_noz) / dp.w18,
            (d.eta_mech_hp * hpt.power - power_hpc - offtake) / dp.power_hp,
            (d.eta_mech_lp * lpt.power - power_fan - power_lpc) / dp.power_lp,
        ]
    )
    sm_fan = maps.surge_margin(d.fan, dp.wc_fan, d.pr_fan_d, w2c, pr_fan, h["fan"][1])
    sm_lpc = maps.surge_margin(d.lpc, dp.wc_lpc, d.pr_lpc_d, w21c, pr_lpc, h["lpc"][1])
    sm_hpc = maps.surge_margin(d.hpc, dp.wc_hpc, d.pr_hpc_d, w25c, pr_hpc, h["hpc"][1])
    stations = Stations(
        t2=t2, p2=p2, p_amb=p_amb, t21=t21, p21=p21, t24=t24, p24=p24, t25=t25, p25=p25,
        t30=t30, p30=p30, t4=burner.t4, p40=p40, t41=hpt.t_rotor_in, t48=hpt.t_out,
        p45=p45, t50=lpt.t_out, p50=p50, p15=p15, nf=nf, nc=nc,
        nf_dmd=nf, pcn_dmd=pcn, wf=wf, far=burner.far, w2=w2, w_core=w_core,
        w_byp=w_byp, w31=w31, w32=w32, w_cust=w_cust, w48=hpt.w_out, w50=lpt.w_out,
        w8_noz=w8_noz, w18_noz=w18_noz, power_fan=power_fan, power_lpc=power_lpc,
        power_hpc=power_hpc, power_hpt=hpt.power, power_lpt=lpt.power,
        power_offtake=offtake, sm_fan=sm_fan, sm_lpc=sm_lpc, sm_hpc=sm_hpc,
        h_bleed32=h32,
    )  # fmt: skip
    return residuals, stations
