"""The gas path of the off-design balance, stage by stage (:func:`.cycle.balance`).

Each stage takes the unknowns z (:mod:`.cycle`) it needs and returns a small record of
the stations that downstream stages, the residuals and the sensors read: the inlet and
the speed controller, the fan and the flow split, the LPC, the HPC with its bleeds, the
hot section (burner, HPT, LPT) and the nozzles. The stages are traced in gas-path order
with every operation where the one-function balance had it, so the traced program, and
every bit of the engine's outputs, is that of the single function.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxcal.models.turbofan.physics import components, maps, thermo
from jaxcal.models.turbofan.physics.atmosphere import free_stream
from jaxcal.models.turbofan.physics.constants import P_STD_PSIA, T_STD_R
from jaxcal.models.turbofan.physics.design import (
    EngineDesign,
    corrected_fan_speed_demand,
    inlet_recovery,
)
from jaxcal.models.turbofan.physics.nozzle import nozzle_flow


class Inlet(NamedTuple):
    """Engine inlet conditions and the fan speed the controller sets (one sample)."""

    t2: jnp.ndarray  # the true inlet temperature (reading + t2_offset) [degR]
    p_amb: jnp.ndarray
    p2: jnp.ndarray
    theta2: jnp.ndarray
    delta2: jnp.ndarray
    pcn: jnp.ndarray  # corrected fan speed demand [%]
    nf: jnp.ndarray  # physical fan speed [rpm]


class CompressorPoint(NamedTuple):
    """One compressor's operating point (one sample)."""

    wc_map: jnp.ndarray  # corrected flow the health-modified map passes at (N, beta)
    wc_in: jnp.ndarray  # corrected flow the gas path delivers (W2c, W21c, W25c)
    pr: jnp.ndarray
    t_out: jnp.ndarray
    p_out: jnp.ndarray
    dh: jnp.ndarray  # specific work [BTU/lbm]


class Core(NamedTuple):
    """The HPC and its bleeds: what the burner, the turbines and the HP shaft see."""

    hpc: CompressorPoint
    t25: jnp.ndarray
    p25: jnp.ndarray
    nc: jnp.ndarray  # physical HP spool speed [rpm]
    w31: jnp.ndarray  # HPT cooling bleed
    w32: jnp.ndarray  # LPT cooling bleed
    w_cust: jnp.ndarray  # customer bleed (effect)
    w3b: jnp.ndarray  # burner inlet flow
    power_hpc: jnp.ndarray
    h30: jnp.ndarray
    h32: jnp.ndarray  # enthalpy of the LPT cooling bleed


class HotSection(NamedTuple):
    """Burner and the two turbines (one sample)."""

    burner: components.Burner
    wf: jnp.ndarray
    p40: jnp.ndarray
    hpt: components.TurbineExit
    phi_hpt_map: jnp.ndarray
    p45: jnp.ndarray
    p45l: jnp.ndarray  # LPT inlet pressure
    lpt: components.TurbineExit
    phi_lpt_map: jnp.ndarray
    p50: jnp.ndarray


def inlet_stage(d: EngineDesign, alt, mach, tra, t2_meas, effects) -> Inlet:
    """Free stream, inlet recovery and the speed controller."""
    t2 = t2_meas + effects[0]
    _, p_amb, pt0 = free_stream(alt, mach, t2)
    p2 = (inlet_recovery(d, mach) + effects[5]) * pt0
    theta2, delta2 = t2 / T_STD_R, p2 / P_STD_PSIA
    # controller: corrected demand on the *measured* T2
    pcn, nrf_dmd = corrected_fan_speed_demand(d, tra)
    nf = nrf_dmd * jnp.sqrt(t2_meas / T_STD_R)
    return Inlet(t2, p_amb, p2, theta2, delta2, pcn, nf)


def compressor_health_map(shape, wc_d, pr_d, eta_d, n, dbeta, health, mode):
    """(corrected flow, PR, efficiency) of a map at (n, beta_d + dbeta), with the
    component's (efficiency, flow) health modifiers applied."""
    beta = maps.BETA_DESIGN + dbeta
    wc, pr, eta = maps.compressor_map(shape, wc_d, pr_d, eta_d, n, beta)
    wc = wc * (1.0 + health[1])
    return wc, pr, maps.apply_efficiency_modifier(eta, health[0], mode)


def fan_stage(d, dp, inlet: Inlet, health, mode, z, unroll):
    """The fan and the flow split: (fan, w2, w_core, w_byp)."""
    n_fan = inlet.nf / jnp.sqrt(inlet.theta2) / dp.nrf
    wc_fan, pr_fan, eta_fan = compressor_health_map(
        d.fan, dp.wc_fan, d.pr_fan_d, d.eta_fan_d, n_fan, z[2], health, mode
    )
    w2c = dp.wc_fan * jnp.exp(z[0])
    w2 = w2c * inlet.delta2 / jnp.sqrt(inlet.theta2)
    bpr = d.bpr_d * jnp.exp(z[1])
    w_core = w2 / (1.0 + bpr)
    w_byp = w2 - w_core
    t21, dh_fan = thermo.compress(inlet.t2, pr_fan, eta_fan, unroll=unroll)
    p21 = inlet.p2 * pr_fan
    return CompressorPoint(wc_fan, w2c, pr_fan, t21, p21, dh_fan), w2, w_core, w_byp


def lpc_stage(
    d, dp, nf, fan: CompressorPoint, w_core, health, mode, z, unroll
) -> CompressorPoint:
    """The LPC (booster) on the LP shaft, behind the fan duct."""
    p21c = fan.p_out * (1.0 - d.dp_fan_duct)
    n_lpc = nf * d.gear_ratio / jnp.sqrt(fan.t_out / T_STD_R) / dp.nc_lpc
    wc_lpc, pr_lpc, eta_lpc = compressor_health_map(
        d.lpc, dp.wc_lpc, d.pr_lpc_d, d.eta_lpc_d, n_lpc, z[3], health, mode
    )
    w21c = w_core * jnp.sqrt(fan.t_out / T_STD_R) / (p21c / P_STD_PSIA)
    t24, dh_lpc = thermo.compress(fan.t_out, pr_lpc, eta_lpc, unroll=unroll)
    p24 = p21c * pr_lpc
    return CompressorPoint(wc_lpc, w21c, pr_lpc, t24, p24, dh_lpc)


def core_stage(
    d, dp, lpc: CompressorPoint, w_core, health, mode, effects, z, unroll
) -> Core:
    """The HPC, its cooling and customer bleeds and the HP shaft's load."""
    t25, p25 = lpc.t_out, lpc.p_out * (1.0 - d.dp_lpc_duct)
    n_hpc = jnp.exp(z[7])
    nc = n_hpc * dp.nc_hpc * jnp.sqrt(t25 / T_STD_R)
    wc_hpc, pr_hpc, eta_hpc = compressor_health_map(
        d.hpc, dp.wc_hpc, d.pr_hpc_d, d.eta_hpc_d, n_hpc, z[4], health, mode
    )
    w25c = w_core * jnp.sqrt(t25 / T_STD_R) / (p25 / P_STD_PSIA)
    t30, dh_hpc = thermo.compress(t25, pr_hpc, eta_hpc, unroll=unroll)
    p30 = p25 * pr_hpc
    w31, w32 = d.bleed_hpt * w_core, d.bleed_lpt * w_core
    w_cust = effects[1] * w_core
    w3b = w_core - w31 - w32 - w_cust
    power_hpc = w_core * dh_hpc - w32 * (1.0 - d.lpt_bleed_work) * dh_hpc
    h30 = thermo.enthalpy(t30)
    h32 = thermo.enthalpy(t25) + d.lpt_bleed_work * dh_hpc
    hpc = CompressorPoint(wc_hpc, w25c, pr_hpc, t30, p30, dh_hpc)
    return Core(hpc, t25, p25, nc, w31, w32, w_cust, w3b, power_hpc, h30, h32)


def turbine_stage(
    shape, eta_d, ntc_d, phi_d, pr_d, gas, pr, speed, w_cool, w_cool_rotor, h_cool,
    health, mode, unroll,
):  # fmt: skip
    """One turbine: cooling mixed ahead of the rotor, map efficiency at the rotor's
    corrected speed, expansion by ``pr``, and the map's flow capacity at ``pr``.

    Args:
        gas: (W, T, FAR) entering the stage; w_cool: the stage's cooling bleed, of
            which w_cool_rotor mixes ahead of the rotor and the rest at its exit.

    Returns:
        (turbine exit, health-modified map flow capacity).
    """
    w_in, far_in, _, t_in = components.mix_cooling(*gas, w_cool_rotor, h_cool, unroll)
    eta = maps.turbine_efficiency(shape, eta_d, speed / jnp.sqrt(t_in) / ntc_d)
    eta = maps.apply_efficiency_modifier(eta, health[0], mode)
    rotor = components.turbine_rotor(
        w_in, t_in, far_in, pr, eta, w_cool - w_cool_rotor, h_cool, unroll
    )
    phi_map = maps.turbine_capacity(shape, phi_d, pr_d, pr)
    return rotor, phi_map * (1.0 + health[1])


def hot_section(d, dp, inlet: Inlet, core: Core, h, mode, z, unroll) -> HotSection:
    """Burner at the solved fuel flow, the HPT and the LPT at their solved PRs."""
    wf = dp.wf_corr * jnp.exp(z[8]) * inlet.delta2 * jnp.sqrt(inlet.theta2)
    burner = components.burner_exit(
        core.w3b, core.hpc.t_out, wf, d.eta_burner, d.lhv, unroll
    )
    p40 = core.hpc.p_out * (1.0 - d.dp_burner)
    # HPT
    pr_hpt = 1.0 + (dp.pr_hpt - 1.0) * jnp.exp(z[5])
    w31r = d.hpt_cool_rotor_frac * core.w31
    hpt, phi_hpt_map = turbine_stage(
        d.hpt, d.eta_hpt_d, dp.ntc_hpt, dp.phi_hpt, dp.pr_hpt,
        (burner.w4, burner.t4, burner.far), pr_hpt, core.nc, core.w31, w31r, core.h30,
        h["hpt"], mode, unroll,
    )  # fmt: skip
    p45 = p40 / pr_hpt
    # LPT
    p45l = p45 * (1.0 - d.dp_hpt_duct)
    pr_lpt = 1.0 + (dp.pr_lpt - 1.0) * jnp.exp(z[6])
    w32r = d.lpt_cool_rotor_frac * core.w32
    n_lp = inlet.nf * d.gear_ratio
    lpt, phi_lpt_map = turbine_stage(
        d.lpt, d.eta_lpt_d, dp.ntc_lpt, dp.phi_lpt, dp.pr_lpt,
        (hpt.w_out, hpt.t_out, hpt.far_out), pr_lpt, n_lp, core.w32, w32r, core.h32,
        h["lpt"], mode, unroll,
    )  # fmt: skip
    p50 = p45l / pr_lpt
    return HotSection(
        burner, wf, p40, hpt, phi_hpt_map, p45, p45l, lpt, phi_lpt_map, p50
    )


def nozzle_flows(
    d, dp, mach, effects, inlet: Inlet, fan: CompressorPoint, hot: HotSection
):
    """The flows the core and bypass nozzles pass: (w8, P15, w18)."""
    lpt = hot.lpt
    p8 = hot.p50 * (1.0 - d.dp_lpt_duct)
    a8 = dp.a8 * (1.0 + effects[3])
    w8_noz, _ = nozzle_flow(
        p8, lpt.t_out, inlet.p_amb, a8, thermo.gamma(lpt.t_out, lpt.far_out), d.cd_core
    )
    p15 = fan.p_out * (1.0 - d.dp_bypass)
    a18 = dp.a18 * (1.0 + d.vafn_slope * (d.mach_d - mach)) * (1.0 + effects[4])
    w18_noz, _ = nozzle_flow(
        p15, fan.t_out, inlet.p_amb, a18, thermo.gamma(fan.t_out), d.cd_bypass
    )
    return w8_noz, p15, w18_noz
