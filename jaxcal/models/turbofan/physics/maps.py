"""Smooth analytic component maps (physics_facts.md 3.1 and 3.3).

Real map tables are piecewise linear and give kinks in the Jacobian of the balance;
these closed forms are C-infinity, so a fixed-iteration Newton solve and implicit
gradients stay well behaved. Every map is *scaled* at the design point (pyCycle
``MapScalars`` / T-MATS convention): at relative corrected speed n = 1 and map
coordinate beta = beta_d the map returns exactly the design corrected flow, pressure
ratio and efficiency.

Compressor (n = Nc/Nc_d, beta in about [0, 1], 0 = choke side, 1 = surge side):

    Wc  = Wc_d n^a (1 + k_w (beta_d - beta))
    PR  = 1 + (PR_d - 1) n^b (1 + k_p (beta - beta_d))
    eta = eta_d [1 - c_n ((n - n_pk)^2 - (1 - n_pk)^2)
                   - c_b ((beta - b_pk)^2 - (beta_d - b_pk)^2)]

Far outside the mapped region the pressure rise and the efficiency island are floored by
softplus functions (physics_facts.md 3.3: "keep it positive with a softplus floor"), so
that extreme health modifiers at idle still give a physical compressor. Health modifiers
act on the scaled map: Wc (1 + dW) and eta (1 + d_eta) ("multiplicative",
the default) or eta + d_eta ("additive"; NASA does not say which N-CMAPSS uses,
data_facts.md 2.2). The surge line is the speed line end beta = 1.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

BETA_DESIGN = 0.5
BETA_SURGE = 1.0


@struct.dataclass
class CompressorShape:
    """Dimensionless shape of a compressor map (fitted, shared by all conditions)."""

    flow_speed_exp: jnp.ndarray  # a: Wc ~ n^a on the design beta line
    flow_slope: jnp.ndarray  # k_w: relative flow change from beta_d to beta_d + 1
    pr_speed_exp: jnp.ndarray  # b: (PR - 1) ~ n^b (pressure rise ~ U^2)
    pr_slope: jnp.ndarray  # k_p: relative (PR - 1) change along a speed line
    eff_speed_curv: jnp.ndarray  # c_n: efficiency island curvature in speed
    eff_beta_curv: jnp.ndarray  # c_b: efficiency island curvature along the line
    eff_speed_peak: jnp.ndarray  # n_pk: speed of peak efficiency
    eff_beta_peak: jnp.ndarray  # b_pk: beta of peak efficiency


@struct.dataclass
class TurbineShape:
    """Turbine efficiency / capacity shape (fitted)."""

    eff_speed_curv: jnp.ndarray  # c: eta = eta_d [1 - c (n_T - 1)^2]
    capacity_exp: jnp.ndarray  # k: ellipse law Wc_T ~ sqrt(1 - PR^-k)


def apply_efficiency_modifier(eta, mod, mode: str):
    """Health modifier on an efficiency: eta (1 + mod) or eta + mod."""
    if mode == "multiplicative":
        return eta * (1.0 + mod)
    if mode == "additive":
        return eta + mod
    raise ValueError(
        f"health_mode must be 'multiplicative' or 'additive', got {mode!r}"
    )


def compressor_map(shape: CompressorShape, wc_d, pr_d, eta_d, n, beta):
    """Scaled compressor map.

    Args:
        shape: map shape parameters.
        wc_d, pr_d, eta_d: design corrected flow, pressure ratio, efficiency.
        n: relative corrected speed Nc/Nc_d.
        beta: map coordinate (beta_d = 0.5 at design).

    Returns:
        (Wc, PR, eta) before health modifiers.
    """
    db = beta - BETA_DESIGN
    wc = wc_d * n**shape.flow_speed_exp * (1.0 - shape.flow_slope * db)
    # far on the choke side the pressure rise goes to zero smoothly instead of turning
    # the compressor into a turbine; identical (to 1e-9) on the mapped region
    rise = _soft_positive(1.0 + shape.pr_slope * db, PR_RISE_FLOOR)
    pr = 1.0 + (pr_d - 1.0) * n**shape.pr_speed_exp * rise
    dn = (n - shape.eff_speed_peak) ** 2 - (1.0 - shape.eff_speed_peak) ** 2
    dbeta = (beta - shape.eff_beta_peak) ** 2 - (BETA_DESIGN - shape.eff_beta_peak) ** 2
    island = 1.0 - shape.eff_speed_curv * dn - shape.eff_beta_curv * dbeta
    eta = eta_d * (EFF_FLOOR + _soft_positive(island - EFF_FLOOR, 0.02))
    return wc, pr, eta


PR_RISE_FLOOR = 0.05  # softplus width of the pressure-rise floor
EFF_FLOOR = 0.3  # efficiency island floor, relative to the design efficiency


def _soft_positive(y, width):
    """softplus with the given width: y for y >> width, > 0 always."""
    return width * jnp.logaddexp(0.0, y / width)


def surge_margin(shape: CompressorShape, wc_d, pr_d, wc, pr, flow_mod):
    """Surge margin SM = PR_surge(Wc)/PR - 1 at the current corrected flow.

    The surge line is beta = 1 of the (health-modified) map; its speed at the current
    corrected flow follows from inverting the power-law flow characteristic.
    """
    line = (
        wc_d * (1.0 + flow_mod) * (1.0 - shape.flow_slope * (BETA_SURGE - BETA_DESIGN))
    )
    n_s = (wc / line) ** (1.0 / shape.flow_speed_exp)
    pr_s = 1.0 + (pr_d - 1.0) * n_s**shape.pr_speed_exp * (
        1.0 + shape.pr_slope * (BETA_SURGE - BETA_DESIGN)
    )
    return pr_s / pr - 1.0


def turbine_capacity(shape: TurbineShape, phi_d, pr_d, pr):
    """Ellipse-law flow capacity W sqrt(Tt)/Pt at pressure ratio PR (> 1)."""
    k = shape.capacity_exp
    return phi_d * jnp.sqrt((1.0 - pr ** (-k)) / (1.0 - pr_d ** (-k)))


def turbine_efficiency(shape: TurbineShape, eta_d, n_rel):
    """Turbine efficiency vs relative corrected speed (N/sqrt(Tt))/(N/sqrt(Tt))_d."""
    return eta_d * (1.0 - shape.eff_speed_curv * (n_rel - 1.0) ** 2)
