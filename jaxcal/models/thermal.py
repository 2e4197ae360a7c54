"""A heated body with two thermal masses: a small example model with memory.

A heater of power ``P`` warms a core (heat capacity ``C_core``), which passes heat
through a resistance ``R_cs`` to a shell (``C_shell``), which loses it to the ambient
through the insulation ``R_sa`` (the resistance that degrades: insulation ages,
``R_sa`` falls). The two temperatures are hidden states, integrated over one sample
``DT`` by the exact exponential of the linear two-node network (RC thermal network;
Incropera et al., *Fundamentals of Heat and Mass Transfer*, sec. 5.9 lumped
capacitance). Outputs: the core and shell temperatures (K; each equals a state, so
a sensor bias on either pins a state) and the heat flow to the ambient (W).
Conditions: heater power (W) and ambient temperature (K).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.model import Model

DT = 60.0  # s per sample
CONDITIONS = {"power": "W", "ambient": "K"}
PARAMETERS = {
    "R_sa": (0.02, 0.01, 0.03, "K/W"),  # shell -> ambient (insulation)
    "R_cs": (0.01, 0.005, 0.02, "K/W"),  # core -> shell
    "C_core": (2.0e5, 1.0e5, 4.0e5, "J/K"),
    "C_shell": (5.0e4, 2.5e4, 1.0e5, "J/K"),
}
OUTPUTS = {"T_core": "K", "T_shell": "K", "q_loss": "W"}
STATES = {"core": "K", "shell": "K"}  # temperatures (the outputs T_core, T_shell)
CONDITION_RANGE = ([0.0, 250.0], [3000.0, 320.0])


def _system_matrix(theta):
    """``A`` of ``dz/dt = A (z - z_ss)`` (the two-node network about its rest)."""
    r_sa, r_cs, c_core, c_shell = theta[0], theta[1], theta[2], theta[3]
    return jnp.array(
        [
            [-1.0 / (r_cs * c_core), 1.0 / (r_cs * c_core)],
            [1.0 / (r_cs * c_shell), -(1.0 / r_cs + 1.0 / r_sa) / c_shell],
        ]
    )


def _expm2(a):
    """``exp(a)`` of a 2x2 matrix with real eigenvalues, in closed form.

    By Cayley–Hamilton, ``exp(A) = e^m (cosh(d) I + sinh(d) / d (A - m I))`` with
    ``m = tr(A) / 2`` and ``d^2 = m^2 - det(A)`` (Moler & Van Loan 2003, polynomial
    methods). The RC network's matrix is similar to a symmetric one, so ``d`` is
    real; the closed form is exact and, evaluated at every step of a simulation,
    about 25x cheaper than the scaled Padé approximation of
    ``jax.scipy.linalg.expm``.
    """
    m = 0.5 * (a[0, 0] + a[1, 1])
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    d = jnp.sqrt(jnp.maximum(m * m - det, 1e-300))
    eye = jnp.eye(2, dtype=a.dtype)
    return jnp.exp(m) * (jnp.cosh(d) * eye + (jnp.sinh(d) / d) * (a - m * eye))


def steady_state(w, theta):
    """``[T_core, T_shell]`` at rest under the conditions ``w``."""
    power, ambient = w[0], w[1]
    shell = ambient + power * theta[0]
    return jnp.stack([shell + power * theta[1], shell])


def thermal_step(z, w, theta):
    """``(z', x)``: one sample of the two-node network (exact for constant ``w``)."""
    z_ss = steady_state(w, theta)
    z_next = z_ss + _expm2(_system_matrix(theta) * DT) @ (z - z_ss)
    q_loss = (z_next[1] - w[1]) / theta[0]
    return z_next, jnp.stack([z_next[0], z_next[1], q_loss])


def thermal_model() -> Model:
    """The two-mass heated body as a :class:`~jaxcal.model.Model` with memory."""
    return Model.from_step(
        thermal_step,
        init_state=steady_state,
        states=STATES,
        conditions=CONDITIONS,
        parameters=PARAMETERS,
        outputs=OUTPUTS,
        name="thermal",
        condition_range=CONDITION_RANGE,
    )
