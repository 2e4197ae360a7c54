"""The two engine configurations, ``cmapss`` and ``agtf30``: nominal design constants.

Nominal values come from physics_facts.md (sections 2, 5 and 6); the constants that the
data determine are then fitted by ``experiments/fit_engine_design.py`` (gradient-based
least squares on the differentiable model) and stored in
``jaxcal/models/turbofan/physics/fitted/<name>.json``, which :func:`load_design` applies
on top of the nominal values. The difference between the two engines is data, not code.
"""

from __future__ import annotations

import dataclasses
import json
from importlib import resources

import jax
import jax.numpy as jnp

from jaxcal.models.turbofan.physics.design import EngineDesign
from jaxcal.models.turbofan.physics.guess import GuessTable
from jaxcal.models.turbofan.physics.maps import CompressorShape, TurbineShape

# PCNfR_dmd(TRA): quadratic through (100 %, 100 %) and (60 %, 84.93 %) from FD002, with
# a curvature that gives about 66.5 % at TRA 23.5 (the lowest N-CMAPSS throttle,
# Nf ~ 1470 rpm); the curvature is refitted with the design constants.
_PCN = dict(pcn_60=84.93, pcn_100=100.0, pcn_curv=-16.75575253)


def _compressor(a, kw, b, kp, cn=0.6, cb=0.4, npk=0.95, bpk=0.45):
    return CompressorShape(
        flow_speed_exp=a, flow_slope=kw, pr_speed_exp=b, pr_slope=kp,
        eff_speed_curv=cn, eff_beta_curv=cb, eff_speed_peak=npk, eff_beta_peak=bpk,
    )  # fmt: skip


CMAPSS_NOMINAL = EngineDesign(
    # design point = sea-level static, standard day, TRA 100 (FD001 / FD002 condition 1)
    alt_d=0.0, mach_d=0.0, pcn_d=100.0,
    w2_d=2750.0, bpr_d=8.42, pr_fan_d=1.5005, eta_fan_d=0.90,
    pr_lpc_d=1.30, eta_lpc_d=0.88, pr_hpc_d=19.7, eta_hpc_d=0.85,
    t4_d=3150.0, eta_hpt_d=0.91, eta_lpt_d=0.92, nc_d=9055.0, gear_ratio=1.0,
    recovery_static=0.9948, recovery_flight=0.997,
    dp_fan_duct=0.005, dp_lpc_duct=0.01, dp_burner=0.045, dp_hpt_duct=0.005,
    dp_lpt_duct=0.01, dp_bypass=0.015, eta_burner=0.999, lhv=18400.0,
    bleed_hpt=0.133, bleed_lpt=0.080, lpt_bleed_work=0.5,
    hpt_cool_rotor_frac=0.4, lpt_cool_rotor_frac=0.5,
    eta_mech_hp=0.99, eta_mech_lp=0.99, hpx_hp=350.0, cd_core=1.0, cd_bypass=1.0,
    ps30_ratio=0.9375, vafn_slope=0.0, nrf_100=2388.0, **_PCN,
    fan=_compressor(1.2, 0.30, 2.0, 0.30),
    lpc=_compressor(1.3, 0.20, 2.0, 0.30),
    hpc=_compressor(2.0, 0.10, 2.0, 0.25),
    hpt=TurbineShape(eff_speed_curv=0.2, capacity_exp=2.0),
    lpt=TurbineShape(eff_speed_curv=0.2, capacity_exp=2.0),
    name="cmapss",
)  # fmt: skip

AGTF30_NOMINAL = EngineDesign(
    # design point = cruise 35 kft, Mach 0.8, ISA, 100 % corrected fan speed (2360 rpm)
    alt_d=35000.0, mach_d=0.8, pcn_d=100.0,
    w2_d=815.5, bpr_d=23.2, pr_fan_d=1.30, eta_fan_d=0.9689,
    pr_lpc_d=3.0, eta_lpc_d=0.8894, pr_hpc_d=14.103, eta_hpc_d=0.8469,
    t4_d=3000.0, eta_hpt_d=0.9313, eta_lpt_d=0.9409, nc_d=20796.0, gear_ratio=3.1,
    recovery_static=0.995, recovery_flight=0.998,
    dp_fan_duct=0.01, dp_lpc_duct=0.015, dp_burner=0.04, dp_hpt_duct=0.005,
    dp_lpt_duct=0.01, dp_bypass=0.015, eta_burner=0.999, lhv=18400.0,
    bleed_hpt=0.10, bleed_lpt=0.05, lpt_bleed_work=0.5,
    hpt_cool_rotor_frac=0.4, lpt_cool_rotor_frac=0.5,
    eta_mech_hp=0.99, eta_mech_lp=0.99, hpx_hp=350.0, cd_core=0.9999,
    cd_bypass=0.9975, ps30_ratio=0.97, vafn_slope=0.403, nrf_100=2360.0, **_PCN,
    fan=_compressor(1.2, 0.40, 2.0, 0.30),
    lpc=_compressor(1.4, 0.20, 2.0, 0.30),
    hpc=_compressor(2.0, 0.10, 2.0, 0.25),
    hpt=TurbineShape(eff_speed_curv=0.2, capacity_exp=2.0),
    lpt=TurbineShape(eff_speed_curv=0.2, capacity_exp=2.0),
    name="agtf30",
)  # fmt: skip

NOMINAL = {"cmapss": CMAPSS_NOMINAL, "agtf30": AGTF30_NOMINAL}


def design_to_flat(design: EngineDesign) -> dict[str, float]:
    """Flatten a design to {"field" or "component.field": float} (JSON friendly)."""
    out = {}
    for f in dataclasses.fields(design):
        if not f.metadata.get("pytree_node", True):
            continue
        v = getattr(design, f.name)
        if dataclasses.is_dataclass(v):
            for g in dataclasses.fields(v):
                out[f"{f.name}.{g.name}"] = float(getattr(v, g.name))
        else:
            out[f.name] = float(v)
    return out


def design_from_flat(base: EngineDesign, flat: dict[str, float]) -> EngineDesign:
    """Replace fields of ``base`` from a flat dict (unknown keys are an error)."""
    valid = design_to_flat(base)
    unknown = sorted(set(flat) - set(valid))
    if unknown:
        raise ValueError(f"unknown design field(s) {unknown}; valid: {sorted(valid)}")
    top, nested = {}, {}
    for k, v in flat.items():
        if "." in k:
            comp, field = k.split(".", 1)
            nested.setdefault(comp, {})[field] = v
        else:
            top[k] = v
    for comp, fields in nested.items():
        top[comp] = dataclasses.replace(getattr(base, comp), **fields)
    return dataclasses.replace(base, **top)


def _fitted_file(name: str) -> dict:
    path = resources.files("jaxcal.models.turbofan.physics") / "fitted" / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def fitted_values(name: str) -> dict[str, float]:
    """The fitted design constants stored with the package ({} if never fitted)."""
    return _fitted_file(name).get("design", {})


def stored_guess_table(name: str):
    """The Newton start table stored with the fit, or None."""
    z = _fitted_file(name).get("guess_table")
    return None if z is None else GuessTable(z=jnp.asarray(z, dtype=float))


def load_design(name: str, *, fitted: bool = True) -> EngineDesign:
    """Design constants of configuration ``name`` (nominal + fitted values).

    Args:
        name: "cmapss" or "agtf30".
        fitted: apply the stored fit (default) or return the nominal values.

    Returns:
        An :class:`EngineDesign` whose leaves are arrays of the default float dtype.
    """
    if name not in NOMINAL:
        raise ValueError(f"unknown engine {name!r}; valid names are {sorted(NOMINAL)}")
    design = NOMINAL[name]
    if fitted:
        design = design_from_flat(design, fitted_values(name))
    return jax.tree.map(lambda v: jnp.asarray(v, dtype=float), design)
