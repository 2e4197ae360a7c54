"""Engine design constants and the design-point calculation.

An engine configuration is *data*: an :class:`EngineDesign` pytree of design-point cycle
values, losses, bleeds, controller schedule and map shapes. :func:`design_point` runs
the cycle once at the design condition in "design mode" (pyCycle's design/off-design
split, physics_facts.md 3.1): compressor pressure ratios, efficiencies and T4 are given;
turbine pressure ratios follow from the shaft power balances and nozzle areas from the
nozzle flow equations. The map scalars it returns make the off-design balance at the
design condition solve exactly at beta = beta_d and relative speeds 1, which is also the
Newton start point. Everything is differentiable, so design constants can be fitted to
data by least squares.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from jaxcal.models.turbofan.physics import components, thermo
from jaxcal.models.turbofan.physics.atmosphere import free_stream, isa_total_temperature
from jaxcal.models.turbofan.physics.constants import HP_PER_BTU_S, P_STD_PSIA, T_STD_R
from jaxcal.models.turbofan.physics.maps import CompressorShape, TurbineShape
from jaxcal.models.turbofan.physics.nozzle import nozzle_flow


@struct.dataclass
class EngineDesign:
    """Design constants of one engine configuration (every leaf a float64 scalar)."""

    # design condition (corrected fan speed at 100 % demand is nrf_100)
    alt_d: jnp.ndarray  # ft
    mach_d: jnp.ndarray
    pcn_d: jnp.ndarray  # % corrected fan speed demand at the design point
    # cycle at the design point
    w2_d: jnp.ndarray  # total inlet flow [lbm/s]
    bpr_d: jnp.ndarray
    pr_fan_d: jnp.ndarray
    eta_fan_d: jnp.ndarray
    pr_lpc_d: jnp.ndarray
    eta_lpc_d: jnp.ndarray
    pr_hpc_d: jnp.ndarray
    eta_hpc_d: jnp.ndarray
    t4_d: jnp.ndarray  # burner exit [degR]
    eta_hpt_d: jnp.ndarray
    eta_lpt_d: jnp.ndarray
    nc_d: jnp.ndarray  # physical HP spool speed at design [rpm]
    gear_ratio: jnp.ndarray  # LP-shaft (LPC, LPT) speed / fan speed; 1 = direct drive
    # inlet, ducts, burner
    recovery_static: jnp.ndarray  # P2/Pt0 at Mach 0
    recovery_flight: jnp.ndarray  # P2/Pt0 at Mach >~ 0.4
    dp_fan_duct: jnp.ndarray  # fan exit -> LPC inlet dP/P
    dp_lpc_duct: jnp.ndarray  # LPC exit -> HPC inlet
    dp_burner: jnp.ndarray
    dp_hpt_duct: jnp.ndarray  # HPT exit -> LPT inlet
    dp_lpt_duct: jnp.ndarray  # LPT exit -> core nozzle
    dp_bypass: jnp.ndarray  # fan exit -> P15 (N-CMAPSS: P15 = 0.985 P21)
    eta_burner: jnp.ndarray
    lhv: jnp.ndarray  # BTU/lbm
    # cooling bleeds (fractions of HPC inlet flow W25)
    bleed_hpt: jnp.ndarray  # W31 / W25, from the HPC exit
    bleed_lpt: jnp.ndarray  # W32 / W25, from an HPC interstage port
    lpt_bleed_work: jnp.ndarray  # fraction of HPC work done on W32 before extraction
    hpt_cool_rotor_frac: jnp.ndarray  # part of W31 mixed ahead of the HPT rotor
    lpt_cool_rotor_frac: jnp.ndarray  # part of W32 mixed ahead of the LPT rotor
    # shafts and nozzles
    eta_mech_hp: jnp.ndarray
    eta_mech_lp: jnp.ndarray
    hpx_hp: jnp.ndarray  # HP shaft power offtake [hp]
    cd_core: jnp.ndarray
    cd_bypass: jnp.ndarray
    ps30_ratio: jnp.ndarray  # Ps30 / P30 (HPC exit static / total)
    vafn_slope: jnp.ndarray  # A18 = A18_d (1 + vafn_slope (M_d - M)); 0 = fixed nozzle
    # power management, u = TRA/100: PCNfR_dmd[%] = pcn_100 + (u - 1) (pcn_100 - pcn_60)
    # / 0.4 + pcn_curv (u - 1)(u - 0.6), i.e. through the two FD002 points + a curvature
    pcn_60: jnp.ndarray
    pcn_100: jnp.ndarray
    pcn_curv: jnp.ndarray
    nrf_100: jnp.ndarray  # corrected fan speed at 100 % [rpm]
    # map shapes
    fan: CompressorShape
    lpc: CompressorShape
    hpc: CompressorShape
    hpt: TurbineShape
    lpt: TurbineShape
    # static choices
    name: str = struct.field(pytree_node=False, default="engine")
    health_mode: str = struct.field(pytree_node=False, default="multiplicative")


@struct.dataclass
class DesignPoint:
    """Map scalars and reference values derived from an :class:`EngineDesign`."""

    wc_fan: jnp.ndarray
    wc_lpc: jnp.ndarray
    wc_hpc: jnp.ndarray
    nrf: jnp.ndarray  # corrected fan speed at design [rpm]
    nc_lpc: jnp.ndarray  # LPC corrected speed (on T21) at design
    nc_hpc: jnp.ndarray  # HPC corrected speed (on T25) at design
    phi_hpt: jnp.ndarray  # W sqrt(T)/P at the HPT NGV
    phi_lpt: jnp.ndarray
    pr_hpt: jnp.ndarray
    pr_lpt: jnp.ndarray
    ntc_hpt: jnp.ndarray  # N/sqrt(T_rotor_in) at design
    ntc_lpt: jnp.ndarray
    a8: jnp.ndarray  # core nozzle area [in^2]
    a18: jnp.ndarray  # bypass nozzle area [in^2]
    wf_corr: jnp.ndarray  # Wf/(delta2 sqrt(theta2)) at design
    w8: jnp.ndarray
    w18: jnp.ndarray
    power_hp: jnp.ndarray  # HP spool power [BTU/s] (residual scale)
    power_lp: jnp.ndarray


def inlet_recovery(design: EngineDesign, mach):
    """P2/Pt0: smooth rise from the static to the flight value (AGTF30-like table)."""
    s = mach**2 / (mach**2 + 0.04)
    return (
        design.recovery_static + (design.recovery_flight - design.recovery_static) * s
    )


def corrected_fan_speed_demand(design: EngineDesign, tra):
    """Power management: TRA [%] -> (PCNfR_dmd [%], NRf_dmd [rpm]) (physics_facts 5)."""
    c0, c1, c2 = schedule_coefficients(design)
    u = tra / 100.0
    pcn = c0 + c1 * u + c2 * u**2
    return pcn, design.nrf_100 * pcn / 100.0


def schedule_coefficients(design: EngineDesign):
    """(c0, c1, c2) of PCNfR_dmd = c0 + c1 u + c2 u^2 from the schedule fields."""
    slope = (design.pcn_100 - design.pcn_60) / 0.4
    c2 = design.pcn_curv
    c1 = slope - 1.6 * c2
    c0 = design.pcn_100 - slope + 0.6 * c2
    return c0, c1, c2


def _turbine_for_work(gas, w_cool, rotor_frac, h_cool, power, eta):
    """A turbine in design mode: the PR that extracts ``power`` from ``gas`` (W, T,
    FAR) after the rotor's share ``rotor_frac`` of the cooling bleed ``w_cool``
    mixed in (the rest mixes at the exit).

    Returns:
        (PR, turbine exit, rotor inlet temperature).
    """
    w_rotor = rotor_frac * w_cool
    w_in, far_in, h_in, t_in = components.mix_cooling(*gas, w_rotor, h_cool)
    pr = components.turbine_pr_for_work(w_in, t_in, far_in, h_in, power, eta)
    rotor = components.turbine_rotor(
        w_in, t_in, far_in, pr, eta, w_cool - w_rotor, h_cool
    )
    return pr, rotor, t_in


def _unit_area_flows(d: EngineDesign, p50, lpt, p21, t21, p_amb):
    """Flows of unit-area core and bypass nozzles at the design point (the areas
    that pass the design flows follow by division)."""
    p8 = p50 * (1.0 - d.dp_lpt_duct)
    w8_unit, _ = nozzle_flow(
        p8, lpt.t_out, p_amb, 1.0, thermo.gamma(lpt.t_out, lpt.far_out)
    )
    p15 = p21 * (1.0 - d.dp_bypass)
    w18_unit, _ = nozzle_flow(p15, t21, p_amb, 1.0, thermo.gamma(t21))
    return w8_unit, w18_unit


def design_point(d: EngineDesign) -> DesignPoint:
    """Run the cycle at the design condition in design mode (see module docstring)."""
    t2 = isa_total_temperature(d.alt_d, d.mach_d)
    _, p_amb, pt0 = free_stream(d.alt_d, d.mach_d, t2)
    p2 = inlet_recovery(d, d.mach_d) * pt0
    theta2, delta2 = t2 / T_STD_R, p2 / P_STD_PSIA
    nrf = d.nrf_100 * d.pcn_d / 100.0
    nf = nrf * jnp.sqrt(theta2)
    w2 = d.w2_d
    w_core = w2 / (1.0 + d.bpr_d)
    w_byp = w2 - w_core
    # fan and booster
    t21, dh_fan = thermo.compress(t2, d.pr_fan_d, d.eta_fan_d)
    p21 = p2 * d.pr_fan_d
    p21c = p21 * (1.0 - d.dp_fan_duct)
    t24, dh_lpc = thermo.compress(t21, d.pr_lpc_d, d.eta_lpc_d)
    p24 = p21c * d.pr_lpc_d
    p25, t25 = p24 * (1.0 - d.dp_lpc_duct), t24
    # HPC with bleeds
    t30, dh_hpc = thermo.compress(t25, d.pr_hpc_d, d.eta_hpc_d)
    p30 = p25 * d.pr_hpc_d
    w31, w32 = d.bleed_hpt * w_core, d.bleed_lpt * w_core
    w3b = w_core - w31 - w32
    power_hpc = w_core * dh_hpc - w32 * (1.0 - d.lpt_bleed_work) * dh_hpc
    h30 = thermo.enthalpy(t30)
    h32 = thermo.enthalpy(t25) + d.lpt_bleed_work * dh_hpc
    # burner
    far = components.burner_far_for_t4(t30, d.t4_d, d.eta_burner, d.lhv)
    wf = far * w3b
    w4 = w3b + wf
    p40 = p30 * (1.0 - d.dp_burner)
    phi_hpt = w4 * jnp.sqrt(d.t4_d) / p40
    # HPT: work from the HP shaft balance
    power_hpt = (power_hpc + d.hpx_hp / HP_PER_BTU_S) / d.eta_mech_hp
    pr_hpt, hpt, t41 = _turbine_for_work(
        (w4, d.t4_d, far), w31, d.hpt_cool_rotor_frac, h30, power_hpt, d.eta_hpt_d
    )
    p45 = p40 / pr_hpt
    # LPT: work from the LP shaft balance
    p45l = p45 * (1.0 - d.dp_hpt_duct)
    phi_lpt = hpt.w_out * jnp.sqrt(hpt.t_out) / p45l
    power_lpt = (w2 * dh_fan + w_core * dh_lpc) / d.eta_mech_lp
    pr_lpt, lpt, t46 = _turbine_for_work(
        (hpt.w_out, hpt.t_out, hpt.far_out), w32, d.lpt_cool_rotor_frac, h32,
        power_lpt, d.eta_lpt_d,
    )  # fmt: skip
    p50 = p45l / pr_lpt
    # nozzles: areas that pass the design flows
    w8_unit, w18_unit = _unit_area_flows(d, p50, lpt, p21, t21, p_amb)
    n_lp = nf * d.gear_ratio
    return DesignPoint(
        wc_fan=w2 * jnp.sqrt(theta2) / delta2,
        wc_lpc=w_core * jnp.sqrt(t21 / T_STD_R) / (p21c / P_STD_PSIA),
        wc_hpc=w_core * jnp.sqrt(t25 / T_STD_R) / (p25 / P_STD_PSIA),
        nrf=nrf,
        nc_lpc=n_lp / jnp.sqrt(t21 / T_STD_R),
        nc_hpc=d.nc_d / jnp.sqrt(t25 / T_STD_R),
        phi_hpt=phi_hpt,
        phi_lpt=phi_lpt,
        pr_hpt=pr_hpt,
        pr_lpt=pr_lpt,
        ntc_hpt=d.nc_d / jnp.sqrt(t41),
        ntc_lpt=n_lp / jnp.sqrt(t46),
        a8=lpt.w_out / (w8_unit * d.cd_core),
        a18=w_byp / (w18_unit * d.cd_bypass),
        wf_corr=wf / (delta2 * jnp.sqrt(theta2)),
        w8=lpt.w_out,
        w18=w_byp,
        power_hp=power_hpc,
        power_lp=power_lpt * d.eta_mech_lp,
    )
