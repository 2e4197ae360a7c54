"""An equivalent-circuit battery model (OCV(SOC), R0, one RC pair, capacity) in JAX.

Thevenin / first-order ECM (Plett 2015, "Battery Management Systems vol. I", eqs.
2.4, 2.22 and 2.26), one sample per step::

    soc'  = soc - I dt / (3600 Q)                          coulomb counting
    v1'   = a v1 + R1 (1 - a) I,   a = exp(-dt / tau1)       RC pair, exact
    V     = OCV(soc') - R0 I - v1'                          terminal voltage

Sign convention: the current ``I`` is positive on discharge (it lowers the SOC and
the terminal voltage); a charge is a negative current. The RC update is the exact
solution of ``dv1/dt = -v1 / tau1 + I / C1`` (``C1 = tau1 / R1``) for a current held
constant over the step (zero-order hold), so the model is exact for any ``dt``:
``dt`` is a condition (seconds since the previous sample), which keeps the model
correct under irregular sampling and gaps. ``current`` is the mean current over
``(t_prev, t]`` and ``V`` the voltage at ``t``.

The state starts at rest at ``soc_0 = SOC_0 = 0.9``, ``v1_0 = 0`` (every cycle of
``make_data.py`` starts there; a filter's initial-state std covers the difference
for other data).

Model error against the PyBaMM SPMe it is checked on: the fresh-cell fit leaves a
voltage RMS of 18.3 mV on a 90-20 % drive cycle (``fit_ecm.py``; two RC pairs only
bring it to 16.9 mV), mostly the SPMe's slow graphite diffusion moving the surface
stoichiometry along the OCV curve's plateaus, which no constant-R ECM follows.

OCV(SOC) is a piecewise-cubic Hermite (PCHIP) curve on 41 uniform SOC knots, fitted
to the PyBaMM ``Chen2020`` (LG M50) parameter set's open-circuit voltage,
``U_p(y(soc)) - U_n(x(soc))`` between its 0 % and 100 % stoichiometries (2.5 V and
4.2 V); it is C1 (smooth, differentiable) and extended linearly outside [0, 1]. The
knot values and slopes below, and the fresh-cell R0, R1 and tau1, were produced by
``python examples/battery/fit_ecm.py`` (pybamm needed only for that script).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxcal

# ---- fitted by examples/battery/fit_ecm.py (PyBaMM 26.10, Chen2020) -------------
# OCV [V] at soc = 0, 0.025, ..., 1 and its slope dOCV/dsoc [V] (PCHIP)
OCV_VALUES = np.array(
    [
        2.5000000, 2.9212338, 3.1094460, 3.2106903, 3.2959070, 3.3786845, 3.4338947,
        3.4641154, 3.4851888, 3.5055888, 3.5285632, 3.5544815, 3.5814460, 3.6067712,
        3.6290478, 3.6486759, 3.6670066, 3.6855156, 3.7053974, 3.7272721, 3.7508736,
        3.7750418, 3.7983475, 3.8200155, 3.8405767, 3.8624439, 3.8895866, 3.9206484,
        3.9479064, 3.9713227, 3.9943045, 4.0181241, 4.0420800, 4.0639895, 4.0809118,
        4.0910693, 4.0966562, 4.1047526, 4.1235529, 4.1564283, 4.2000000,
    ]
)  # fmt: skip
OCV_SLOPES = np.array(
    [
        21.5098, 10.4070, 5.2665, 3.7017, 3.3592, 2.6496, 1.5624, 0.9933,
        0.8293, 0.8644, 0.9743, 1.0572, 1.0448, 0.9481, 0.8347, 0.7583,
        0.7368, 0.7668, 0.8332, 0.9082, 0.9553, 0.9492, 0.8983, 0.8440,
        0.8478, 0.9688, 1.1588, 1.1614, 1.0077, 0.9279, 0.9357, 0.9555,
        0.9155, 0.7638, 0.5078, 0.2884, 0.2645, 0.4527, 0.9568, 1.4990,
        1.9568,
    ]
)  # fmt: skip
# fresh cell (Chen2020, 25 degC), least squares on a PyBaMM SPMe drive cycle
R0_FRESH = 0.02824  # [Ohm]
R1_FRESH = 0.01986  # [Ohm]
TAU1_FRESH = 101.56  # [s]
Q_FRESH = 5.15320  # [Ah] between the 0 % and 100 % stoichiometries
# ----------------------------------------------------------------------------------
SOC_0 = 0.9  # initial state of charge (make_data.SOC_START)


def ocv(soc, values=OCV_VALUES, slopes=OCV_SLOPES):
    """Open-circuit voltage ``[V]`` of ``soc`` (any shape): cubic Hermite on uniform
    knots (Fritsch & Carlson 1980 slopes), linear beyond the end knots.

    Args:
        soc: state of charge ``[...]`` (fraction).
        values, slopes: ``[K]`` knot values and slopes ``d OCV / d soc``.
    """
    values = jnp.asarray(values, jnp.result_type(soc))
    slopes = jnp.asarray(slopes, values.dtype)
    num = values.shape[0] - 1
    h = 1.0 / num
    s = jnp.clip(soc, 0.0, 1.0)
    k = jnp.clip(jnp.floor(s * num).astype(jnp.int32), 0, num - 1)
    u = (s - k * h) / h  # position inside the interval, [0, 1]
    h00 = (1 + 2 * u) * (1 - u) ** 2
    h10 = u * (1 - u) ** 2
    h01 = u**2 * (3 - 2 * u)
    h11 = u**2 * (u - 1)
    inside = (
        h00 * values[k] + h10 * h * slopes[k] + h01 * values[k + 1]
        + h11 * h * slopes[k + 1]
    )  # fmt: skip
    # linear extension keeps the curve C1 and invertible outside [0, 1]
    below = jnp.minimum(soc, 0.0) * slopes[0]
    above = jnp.maximum(soc - 1.0, 0.0) * slopes[-1]
    return inside + below + above


def step(state, w, theta):
    """One sample of the ECM (module docstring).

    Args:
        state: ``[2]`` ``(soc [-], v_rc1 [V])``.
        w: ``[2]`` ``(current [A], discharge positive; dt [s])``.
        theta: ``[4]`` ``(R0 [Ohm], R1 [Ohm], tau1 [s], Q [Ah])``.

    Returns:
        ``(next_state [2], x [1] = (voltage [V],))``.
    """
    current, dt = w[0], w[1]
    r0, r1, tau1, capacity = theta[0], theta[1], theta[2], theta[3]
    soc = state[0] - current * dt / (3600.0 * capacity)
    decay = jnp.exp(-dt / tau1)
    v_rc1 = decay * state[1] + r1 * (1.0 - decay) * current
    voltage = ocv(soc) - r0 * current - v_rc1
    return jnp.stack([soc, v_rc1]), voltage[None]


PARAMETERS = {
    "R0": (R0_FRESH, 0.002, 0.08, "Ohm"),
    "R1": (R1_FRESH, 0.001, 0.08, "Ohm"),
    "tau1": (TAU1_FRESH, 5.0, 400.0, "s"),
    "Q": (Q_FRESH, 2.5, 6.0, "Ah"),
}

MODEL = jaxcal.Model.from_step(
    step,
    init_state=np.array([SOC_0, 0.0]),
    states=(("soc", "-"), ("v_rc1", "V")),
    conditions=(("current", "A"), ("dt", "s")),
    parameters=PARAMETERS,
    outputs=(("voltage", "V"),),
    name="battery_ecm",
    # |I| <= 6C of the 5 Ah cell; dt from 1 ms to one hour
    condition_range=((-30.0, 1e-3), (30.0, 3600.0)),
)
