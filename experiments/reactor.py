"""The newcomer's reactor (issue 42): a continuous stirred-tank reactor with memory.

An exothermic first-order reaction A -> B in a cooled, well-mixed tank (the textbook
CSTR of Seborg, Edgar & Mellichamp, "Process Dynamics and Control", example 2.5 /
the APMonitor benchmark: V = 100 L, rho Cp = 239 J/(L K), k0 = 7.2e10 / min, E / R =
8750 K, -dH = 5e4 J/mol, UA = 5e4 J/(min K)):

    dC/dt = F / V (C_feed - C) - a k0 exp(-e E / (R T)) C
    dT/dt = F / V (T_feed - T) + h (-dH) / (rho Cp) a k0 exp(-e E / (R T)) C
            - UA / (V rho Cp) (T - T_coolant)

Hidden states: the concentration ``C_A`` (mol/L) and temperature ``T`` (K), both
measured with noise. Conditions: the feed flow ``F`` (L/min), feed temperature and
coolant temperature (K), held over a sample (:data:`DT` minutes, :data:`SUBSTEPS`
classical Runge-Kutta sub-steps). Parameters: the catalyst ``activity`` (a multiple
of k0; it decays), the activation energy's scale ``E_scale``, the heat transfer
``UA`` (1e4 J/(min K)) and the heat of reaction ``dH`` (1e4 J/mol).

:func:`make_fleet` draws units of piecewise-constant conditions, the catalyst activity
falling linearly, and the outputs' noise white or AR(1) (``phi``), with a temperature
sensor bias from a given row on some units (``bias``). ``tests/support/reactor.py``
imports this file for small versions of the same fleet.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

DT = 0.25  # min per sample (the residence time V / F is about 1 min)
SUBSTEPS = 5  # RK4 sub-steps per sample
SETTLE_MINUTES = 20.0  # the initial state: the reactor run this long at w0
VOLUME, C_FEED, RHO_CP = 100.0, 1.0, 239.0  # L, mol/L, J/(L K)
K0, E_OVER_R = 7.2e10, 8750.0  # 1/min, K
CONDITIONS = {"flow": "L/min", "T_feed": "K", "T_coolant": "K"}
PARAMETERS = {
    "activity": (1.0, 0.5, 1.5),
    "E_scale": (1.0, 0.98, 1.02),
    "UA": (5.0, 3.0, 7.0, "1e4 J/(min K)"),
    "dH": (1.5, 1.0, 2.0, "1e4 J/mol"),
}
OUTPUTS = {"C_A": "mol/L", "T": "K"}
STATES = {"conc": "mol/L", "temp": "K"}  # the outputs C_A and T
CONDITION_RANGE = ([60.0, 320.0, 300.0], [140.0, 365.0, 350.0])
NOISE = {"C_A": 0.01, "T": 0.25}  # the sensors' std
THETA = ("activity", "UA")  # calibrated: the drifting activity and the heat transfer


def derivative(z, w, theta):
    """``dz/dt [2]`` of the tank (module doc)."""
    conc, temp = z[0], z[1]
    flow, t_feed, t_cool = w[0], w[1], w[2]
    activity, e_scale, ua, dh = theta[0], theta[1], 1e4 * theta[2], 1e4 * theta[3]
    rate = activity * K0 * jnp.exp(-e_scale * E_OVER_R / temp) * conc
    dilution = flow / VOLUME
    d_conc = dilution * (C_FEED - conc) - rate
    d_temp = (
        dilution * (t_feed - temp)
        + dh / RHO_CP * rate
        - ua / (VOLUME * RHO_CP) * (temp - t_cool)
    )
    return jnp.stack([d_conc, d_temp])


def _rk4(z, w, theta, h):
    k1 = derivative(z, w, theta)
    k2 = derivative(z + 0.5 * h * k1, w, theta)
    k3 = derivative(z + 0.5 * h * k2, w, theta)
    k4 = derivative(z + h * k3, w, theta)
    return z + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def reactor_step(z, w, theta):
    """``(z', x)``: one sample of :data:`DT` minutes by :data:`SUBSTEPS` RK4 steps;
    the outputs are the states at the sample's end."""
    h = DT / SUBSTEPS
    z_next = jax.lax.fori_loop(0, SUBSTEPS, lambda _, z: _rk4(z, w, theta, h), z)
    return z_next, z_next


def settled_state(w, theta):
    """The state after :data:`SETTLE_MINUTES` at the conditions ``w`` from the feed
    (the reactor at rest there: the start of a unit's record)."""
    z0 = jnp.stack([jnp.asarray(C_FEED, w.dtype) * 0.5, w[1]])
    steps = int(SETTLE_MINUTES / DT)
    return jax.lax.fori_loop(0, steps, lambda _, z: reactor_step(z, w, theta)[0], z0)


def reactor_model():
    import jaxcal

    return jaxcal.Model.from_step(
        reactor_step, init_state=settled_state, states=STATES,
        conditions=CONDITIONS, parameters=PARAMETERS, outputs=OUTPUTS,
        name="cstr", condition_range=CONDITION_RANGE,
    )  # fmt: skip


def conditions(rng: np.random.Generator, n: int) -> np.ndarray:
    """``[n, 3]`` flow, feed and coolant temperature, each switched to a new random
    level every 10-40 samples."""
    w = np.empty((n, 3))
    low, high = np.array([80.0, 340.0, 320.0]), np.array([120.0, 360.0, 345.0])
    t = 0
    while t < n:
        d = int(rng.integers(10, 41))
        w[t : t + d] = rng.uniform(low, high)
        t += d
    return w


def ar_noise(rng: np.random.Generator, n: int, phi: float, std) -> np.ndarray:
    """``[n, S]`` AR(1) noise of coefficient ``phi`` and marginal std ``std [S]``
    (stationary from its first row; ``phi = 0``: white)."""
    std = np.asarray(std, np.float64)
    e = rng.standard_normal((n, len(std))) * np.sqrt(1.0 - phi**2)
    out = np.empty_like(e)
    out[0] = rng.standard_normal(len(std))
    for t in range(1, n):
        out[t] = phi * out[t - 1] + e[t]
    return out * std


_SIMULATE = jax.jit(
    lambda w, theta: jax.lax.scan(
        lambda z, inputs: reactor_step(z, *inputs),
        settled_state(w[0], theta[0]),
        (w, theta),
    )[1]
)


def make_fleet(
    seed: int = 0, *, units: int = 6, rows: int = 500, phi: float = 0.0,
    bias: float = 0.0, bias_units=(), bias_from: int = 300, fall=(0.2, 0.4),
) -> pd.DataFrame:  # fmt: skip
    """``units`` units of ``rows`` samples: conditions from :func:`conditions`; the
    catalyst activity falling linearly by a unit's share in ``fall`` from 0.9-1.2,
    the other parameters constant per unit; the outputs' noise :data:`NOISE`, AR(1)
    with ``phi``; ``bias`` K added to the temperature reading from row
    ``bias_from`` on the units ``bias_units`` (1-based). The true parameters are
    columns of the frame."""
    rng = np.random.default_rng([seed, 42])
    names = list(PARAMETERS)
    frames = []
    for u in range(1, units + 1):
        w = conditions(rng, rows)
        theta = np.empty((rows, len(names)))
        start, drop = rng.uniform(0.9, 1.2), rng.uniform(*fall)
        theta[:, 0] = start * (1.0 - drop * np.linspace(0.0, 1.0, rows))
        theta[:, 1] = 1.0
        theta[:, 2] = rng.uniform(4.0, 6.0)
        theta[:, 3] = 1.5
        x = np.asarray(_SIMULATE(jnp.asarray(w), jnp.asarray(theta)), np.float64)
        x = x + ar_noise(rng, rows, phi, list(NOISE.values()))
        if u in bias_units:
            x[bias_from:, 1] += bias
        frame = pd.DataFrame(np.hstack([w, x]), columns=[*CONDITIONS, *OUTPUTS])
        frame["unit"], frame["time"] = u, np.arange(rows)
        for j, name in enumerate(names):
            frame[name] = theta[:, j]
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)
