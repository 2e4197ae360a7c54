"""A two-node thermal model of a heated room (memory), for a held-out check (issue 41).

Room air T_r and wall T_w (states), heater power Q and outdoor temperature T_a
(conditions): C_r dT_r/dt = eta Q - UA_rw (T_r - T_w),
C_w dT_w/dt = UA_rw (T_r - T_w) - UA_wo (T_w - T_a), explicit Euler in 10 sub-steps.
Parameters: the heater's efficiency eta (fouling), UA_rw and UA_wo (insulation
ageing). Outputs: T_r, T_w and the heat flux out, UA_wo (T_w - T_a) / 1000 (kW).
"""

import jax
import jax.numpy as jnp

from jaxcal.model import Model

C_R, C_W, DT, SUB = 2.0e6, 1.5e7, 600.0, 10


def _deriv(z, w, theta):
    t_r, t_w = z[0], z[1]
    q, t_a = w[0] * 1000.0, w[1]
    eta, ua_rw, ua_wo = theta[0], theta[1], theta[2]
    d_r = (eta * q - ua_rw * (t_r - t_w)) / C_R
    d_w = (ua_rw * (t_r - t_w) - ua_wo * (t_w - t_a)) / C_W
    return jnp.stack([d_r, d_w])


def thermal_step(z, w, theta):
    def sub(zz, _):
        return zz + (DT / SUB) * _deriv(zz, w, theta), None

    z, _ = jax.lax.scan(sub, z, None, length=SUB)
    flux = theta[2] * (z[1] - w[1]) / 1000.0
    return z, jnp.stack([z[0], z[1], flux])


def thermal_init(w, theta):
    q, t_a = w[0] * 1000.0, w[1]
    eta, ua_rw, ua_wo = theta[0], theta[1], theta[2]
    t_w = t_a + eta * q / ua_wo
    t_r = t_w + eta * q / ua_rw
    return jnp.stack([t_r, t_w])


def thermal_model() -> Model:
    return Model.from_step(
        thermal_step,
        init_state=thermal_init,
        states={"T_room": "C", "T_wall": "C"},
        conditions={"heater": "kW", "T_out": "C"},
        parameters={
            "eta": (0.95, 0.6, 1.0, "-"),
            "UA_rw": (800.0, 400.0, 1200.0, "W/K"),
            "UA_wo": (300.0, 150.0, 450.0, "W/K"),
        },
        outputs={"T_r": "C", "T_w": "C", "flux": "kW"},
        name="thermal",
        condition_range=([2.0, -10.0], [10.0, 10.0]),
    )
