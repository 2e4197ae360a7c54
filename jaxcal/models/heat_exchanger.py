"""A counterflow heat exchanger (effectiveness-NTU), a small static example model.

Conditions: hot and cold inlet temperatures (K) and mass flows (kg/s). Parameters:
``fouling`` (the conductance ``UA = UA0 (1 - fouling)`` lost to deposits), ``dp_coeff``
(the hot side's pressure-loss coefficient ``dp = k m^2``, grows as the passages
clog) and
``heat_loss`` (the share of the duty lost to the surroundings before it reaches the
cold stream). Outputs: both outlet temperatures (K), the hot-side pressure drop (kPa)
and the duty (kW) measured on the cold side. Equations: Incropera et al.,
*Fundamentals of Heat and Mass Transfer*, eq. 11.29b (counterflow effectiveness).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.model import Model

CP_HOT = 4.18  # kJ/(kg K), water
CP_COLD = 4.18
UA0 = 8.0  # kW/K, clean conductance

CONDITIONS = {"T_hot_in": "K", "T_cold_in": "K", "m_hot": "kg/s", "m_cold": "kg/s"}
PARAMETERS = {
    "fouling": (0.0, 0.0, 0.6, "-"),
    "dp_coeff": (10.0, 5.0, 40.0, "kPa/(kg/s)^2"),
    "heat_loss": (0.02, 0.0, 0.2, "-"),
}
OUTPUTS = {"T_hot_out": "K", "T_cold_out": "K", "dp_hot": "kPa", "duty": "kW"}
# Rated operation: inlet temperatures and flows the model is valid for.
CONDITION_RANGE = ([320.0, 270.0, 0.2, 0.2], [420.0, 320.0, 3.0, 3.0])


def heat_exchanger(w, theta):
    """``x [4] = F(w [4], theta [3])`` (see the module docstring)."""
    t_hot, t_cold, m_hot, m_cold = w[0], w[1], w[2], w[3]
    fouling, dp_coeff, loss = theta[0], theta[1], theta[2]
    c_hot, c_cold = m_hot * CP_HOT, m_cold * CP_COLD
    c_min, c_max = jnp.minimum(c_hot, c_cold), jnp.maximum(c_hot, c_cold)
    ratio = c_min / c_max
    ntu = UA0 * (1.0 - fouling) / c_min
    # eq. 11.29b; at ratio -> 1 it tends to NTU / (1 + NTU) (kept away from 0/0)
    balanced = jnp.abs(1.0 - ratio) < 1e-6
    safe = jnp.where(balanced, 0.5, ratio)
    eff_general = (1.0 - jnp.exp(-ntu * (1.0 - safe))) / (
        1.0 - safe * jnp.exp(-ntu * (1.0 - safe))
    )
    eff = jnp.where(balanced, ntu / (1.0 + ntu), eff_general)
    duty_hot = eff * c_min * (t_hot - t_cold)
    duty_cold = (1.0 - loss) * duty_hot
    dp = dp_coeff * m_hot**2  # quadratic loss in the hot passages
    return jnp.stack(
        [t_hot - duty_hot / c_hot, t_cold + duty_cold / c_cold, dp, duty_cold]
    )


def heat_exchanger_model() -> Model:
    """The heat exchanger as a :class:`~jaxcal.model.Model`."""
    return Model.from_function(
        heat_exchanger,
        conditions=CONDITIONS,
        parameters=PARAMETERS,
        outputs=OUTPUTS,
        name="heat_exchanger",
        condition_range=CONDITION_RANGE,
    )
