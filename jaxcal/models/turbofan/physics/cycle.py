"""Off-design balance of the two-spool separate-flow turbofan (physics_facts.md 4).

Nine unknowns z, all dimensionless and 0 at the design point:

    z0 ln(W2c/W2c_d)   z1 ln(BPR/BPR_d)   z2..z4 beta - beta_d (fan, LPC, HPC)
    z5 ln((PR_HPT-1)/(PR_HPT_d-1))   z6 same for the LPT   z7 ln(NcR_HPC/NcR_HPC_d)
    z8 ln(Wf_corr/Wf_corr_d)

Nine residuals, each normalised by its design value: fan, LPC and HPC flow
compatibility, HPT and LPT flow capacity, core and bypass nozzle flow, HP and LP shaft
power balance. The closure is C-MAPSS-like: the physical fan speed is set by the
corrected-speed demand of the TRA schedule, Nf = NRf_dmd sqrt(T2/518.67), and the fuel
flow is solved.

``effects`` extends the model with the parametric effects the closing-the-loop library
needs (see :data:`EFFECT_NAMES`); all zero reproduces the plain engine. The gas path's
stages (inlet, compressors, hot section, nozzles) are in :mod:`.gas_path`; this module
closes them into the residuals and the stations.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxcal.models.turbofan.physics import gas_path, maps
from jaxcal.models.turbofan.physics.constants import HP_PER_BTU_S
from jaxcal.models.turbofan.physics.design import DesignPoint, EngineDesign

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
            (:func:`jaxcal.models.turbofan.physics.thermo._iterate`).

    Returns:
        (residuals [9], Stations).
    """
    # The stages run in gas-path order, each op where the single-function form had
    # it: the traced program, and so every bit of the output, is unchanged.
    alt, mach, tra, t2_meas = w[0], w[1], w[2], w[3]
    h = unpack_theta(theta)
    mode = d.health_mode
    inlet = gas_path.inlet_stage(d, alt, mach, tra, t2_meas, effects)
    fan, w2, w_core, w_byp = gas_path.fan_stage(d, dp, inlet, h["fan"], mode, z, unroll)
    lpc = gas_path.lpc_stage(d, dp, inlet.nf, fan, w_core, h["lpc"], mode, z, unroll)
    core = gas_path.core_stage(d, dp, lpc, w_core, h["hpc"], mode, effects, z, unroll)
    hot = gas_path.hot_section(d, dp, inlet, core, h, mode, z, unroll)
    w8_noz, p15, w18_noz = gas_path.nozzle_flows(d, dp, mach, effects, inlet, fan, hot)
    burner, hpt, lpt, t21, p21 = hot.burner, hot.hpt, hot.lpt, fan.t_out, fan.p_out
    # shafts
    offtake = (d.hpx_hp + effects[2]) / HP_PER_BTU_S
    power_fan, power_lpc = w2 * fan.dh, w_core * lpc.dh
    residuals = jnp.stack(
        [
            (fan.wc_in - fan.wc_map) / dp.wc_fan,
            (lpc.wc_in - lpc.wc_map) / dp.wc_lpc,
            (core.hpc.wc_in - core.hpc.wc_map) / dp.wc_hpc,
            (burner.w4 * jnp.sqrt(burner.t4) / hot.p40 - hot.phi_hpt_map) / dp.phi_hpt,
            (hpt.w_out * jnp.sqrt(hpt.t_out) / hot.p45l - hot.phi_lpt_map) / dp.phi_lpt,
            (lpt.w_out - w8_noz) / dp.w8,
            (w_byp - w18_noz) / dp.w18,
            (d.eta_mech_hp * hpt.power - core.power_hpc - offtake) / dp.power_hp,
            (d.eta_mech_lp * lpt.power - power_fan - power_lpc) / dp.power_lp,
        ]
    )
    sm_fan = maps.surge_margin(
        d.fan, dp.wc_fan, d.pr_fan_d, fan.wc_in, fan.pr, h["fan"][1]
    )
    sm_lpc = maps.surge_margin(
        d.lpc, dp.wc_lpc, d.pr_lpc_d, lpc.wc_in, lpc.pr, h["lpc"][1]
    )
    sm_hpc = maps.surge_margin(
        d.hpc, dp.wc_hpc, d.pr_hpc_d, core.hpc.wc_in, core.hpc.pr, h["hpc"][1]
    )
    stations = Stations(
        t2=inlet.t2, p2=inlet.p2, p_amb=inlet.p_amb, t21=t21, p21=p21, t24=lpc.t_out,
        p24=lpc.p_out, t25=core.t25, p25=core.p25, t30=core.hpc.t_out,
        p30=core.hpc.p_out, t4=burner.t4, p40=hot.p40, t41=hpt.t_rotor_in,
        t48=hpt.t_out, p45=hot.p45, t50=lpt.t_out, p50=hot.p50, p15=p15, nf=inlet.nf,
        nc=core.nc, nf_dmd=inlet.nf, pcn_dmd=inlet.pcn, wf=hot.wf, far=burner.far,
        w2=w2, w_core=w_core, w_byp=w_byp, w31=core.w31, w32=core.w32,
        w_cust=core.w_cust, w48=hpt.w_out, w50=lpt.w_out, w8_noz=w8_noz,
        w18_noz=w18_noz, power_fan=power_fan, power_lpc=power_lpc,
        power_hpc=core.power_hpc, power_hpt=hpt.power, power_lpt=lpt.power,
        power_offtake=offtake, sm_fan=sm_fan, sm_lpc=sm_lpc, sm_hpc=sm_hpc,
        h_bleed32=core.h32,
    )  # fmt: skip
    return residuals, stations
