"""One engine balance solved: outputs, validity, the envelope (F's core).

:func:`evaluate_design` is the turbofan's F for explicit design constants: the cycle's
balance (:mod:`jaxcal.models.turbofan.physics.cycle`) closed by Newton's method from the
guess table (:mod:`jaxcal.models.turbofan.physics.solver`), vmapped over any batch
shape, with the sensors and the flags that say whether the answer may be used (closed,
finite, physical, inside the :class:`Envelope`).
:class:`jaxcal.models.turbofan.physics.engine.Engine` wraps it with its constants; the
warm-started single-stream form is :mod:`jaxcal.models.turbofan.physics.warm_start`.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.models.turbofan.physics import cycle, solver
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.constants import (
    CONDITION_NAMES,
    HEALTH_NAMES,
    SENSOR_NAMES,
    T_STD_R,
)
from jaxcal.models.turbofan.physics.design import (
    DesignPoint,
    EngineDesign,
    corrected_fan_speed_demand,
    design_point,
)
from jaxcal.models.turbofan.physics.guess import GuessTable, initial_guess
from jaxcal.precision import float_dtype


@dataclasses.dataclass(frozen=True)
class Envelope:
    """Inputs the model is valid for; outside, ``info.converged`` is False."""

    alt_ft: tuple[float, float] = (-1000.0, 45000.0)
    mach: tuple[float, float] = (0.0, 0.9)
    tra_pct: tuple[float, float] = (15.0, 105.0)
    # T2 minus the ISA total temperature at (alt, Mach) [degR]
    t2_dev_r: tuple[float, float] = (-45.0, 60.0)
    # fan and LPC modifiers may go far lower (N-CMAPSS DS04/DS06 reach -0.22 / -0.155)
    theta_fan_lpc: tuple[float, float] = (-0.30, 0.03)
    theta_core: tuple[float, float] = (-0.10, 0.03)

    def theta_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-parameter (low [10], high [10]) in HEALTH_NAMES order."""
        lo = np.array([self.theta_fan_lpc[0]] * 4 + [self.theta_core[0]] * 6)
        hi = np.array([self.theta_fan_lpc[1]] * 4 + [self.theta_core[1]] * 6)
        return lo, hi

    def w_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(low [4], high [4]) of w = (alt, Mach, TRA, T2), a
        :class:`~jaxcal.calibrators.interface.SampleCheck`'s box: T2 bounded by the
        hull of the ISA deviation band (``isa_total_temperature`` is monotone in alt
        and Mach). A sample inside the hull but off the band is caught after the
        step: the engine then gives NaN and the row is flagged ``state_nonfinite``."""
        alt, mach = self.alt_ft, self.mach
        t2_low = float(isa_total_temperature(alt[1], mach[0])) + self.t2_dev_r[0]
        t2_high = float(isa_total_temperature(alt[0], mach[1])) + self.t2_dev_r[1]
        low = np.array([alt[0], mach[0], self.tra_pct[0], t2_low])
        high = np.array([alt[1], mach[1], self.tra_pct[1], t2_high])
        return low, high


class EngineInfo(NamedTuple):
    """How the balance ended, per sample (shapes = batch shape of the call)."""

    converged: jax.Array  # bool: closed, finite and inside the envelope
    residual_norm: jax.Array  # max |normalised residual| at the solution
    iterations: jax.Array  # Newton iterations used
    in_envelope: jax.Array  # bool: inputs inside :class:`Envelope`
    z: jax.Array  # [..., 9] solution (a warm start for a nearby point)


def sensor_vector(d: EngineDesign, st: cycle.Stations, w) -> jax.Array:
    t2_meas = w[3]
    ps30 = d.ps30_ratio * st.p30
    values = {
        "T24": st.t24, "T30": st.t30, "T48": st.t48, "T50": st.t50, "P15": st.p15,
        "P2": st.p2, "P21": st.p21, "P24": st.p24, "Ps30": ps30, "P40": st.p40,
        "P50": st.p50, "Nf": st.nf, "Nc": st.nc, "Wf": st.wf,
        "T40": st.t4, "P30": st.p30, "P45": st.p45, "W21": st.w2, "W22": st.w_core,
        "W25": st.w_core, "W31": st.w31, "W32": st.w32, "W48": st.w48, "W50": st.w50,
        "SmFan": st.sm_fan, "SmLPC": st.sm_lpc, "SmHPC": st.sm_hpc, "phi": st.wf / ps30,
        "epr": st.p50 / st.p2, "NRf": st.nf / jnp.sqrt(t2_meas / T_STD_R),
        "NRc": st.nc / jnp.sqrt(st.t24 / T_STD_R), "BPR": st.w_byp / st.w_core,
        "farB": st.far, "PCNfR_dmd": st.pcn_dmd, "Nf_dmd": st.nf_dmd,
    }  # fmt: skip
    return jnp.stack([values[n] for n in SENSOR_NAMES])


def in_envelope(env: Envelope, w, theta):
    alt, mach, tra, t2 = w[0], w[1], w[2], w[3]
    dev = t2 - isa_total_temperature(alt, mach)
    lo, hi = env.theta_bounds()
    ok = (
        (alt >= env.alt_ft[0]) & (alt <= env.alt_ft[1])
        & (mach >= env.mach[0]) & (mach <= env.mach[1])
        & (tra >= env.tra_pct[0]) & (tra <= env.tra_pct[1])
        & (dev >= env.t2_dev_r[0]) & (dev <= env.t2_dev_r[1])
        & jnp.all(theta >= lo) & jnp.all(theta <= hi)
    )  # fmt: skip
    return ok & jnp.all(jnp.isfinite(w)) & jnp.all(jnp.isfinite(theta))


# A balance can close on a non-physical branch (e.g. a nozzle flowing into a higher
# ambient pressure through the continued flow function): such roots are not "converged".
T4_MAX_R = 4500.0


def physical(st: cycle.Stations):
    return (
        (st.p50 > st.p_amb)
        & (st.p15 > st.p_amb)
        & (st.t4 < T4_MAX_R)
        & (st.w_core > 0.0)
        & (st.wf > 0.0)
    )


def residual_fn(z, params):
    d, dp, w, theta, effects = params
    return cycle.balance(d, dp, w, theta, effects, z)[0]


def balance_outputs(z, params):
    """The balance's residuals, the sensor vector and whether the stations are
    physical at ``z`` (:func:`~jaxcal.models.turbofan.physics.solver.solve_closed`)."""
    d, dp, w, theta, effects = params
    r, st = cycle.balance(d, dp, w, theta, effects, z)
    return r, sensor_vector(d, st, w), physical(st)


def default_solver_config(dtype) -> solver.SolverConfig:
    """F's Newton settings at a float precision: float32 cannot reach float64's
    tolerance, so it stops at 2e-5 and may take more iterations."""
    if dtype == jnp.float64:
        return solver.SolverConfig()
    return solver.SolverConfig(tol=2e-5, max_iter=30)


def evaluate_design(
    d: EngineDesign,
    w,
    theta,
    effects=None,
    z0=None,
    *,
    guess: GuessTable | None = None,
    envelope: Envelope = Envelope(),
    solver_cfg: solver.SolverConfig | None = None,
    dp: DesignPoint | None = None,
):
    """Functional form of :meth:`Engine.evaluate` with the design as an argument.

    Differentiable w.r.t. every leaf of ``d`` (used to fit the design constants).

    Args:
        d: design constants.
        w: [..., 4] operating conditions (alt ft, Mach, TRA %, T2 degR).
        theta: [..., 10] health modifiers (broadcast against w's batch shape).
        effects: [..., NUM_EFFECTS] model extensions (default zeros).
        z0: [..., 9] Newton start (default: ``guess`` interpolated at (TRA, Mach), or
            the design point z = 0 without a table).
        guess: table of solved balances (:mod:`jaxcal.models.turbofan.physics.guess`).
        envelope: validity box for ``info.in_envelope``.
        solver_cfg: Newton settings (default depends on the float precision).
        dp: precomputed design point of ``d`` (optional).

    Returns:
        (x [..., S], EngineInfo) with S = len(SENSOR_NAMES).
    """
    dtype = float_dtype()
    solver_cfg = default_solver_config(dtype) if solver_cfg is None else solver_cfg
    accept = max(100.0 * solver_cfg.tol, 1e-9) if dtype == jnp.float64 else 1e-4
    w = jnp.asarray(w, dtype)
    theta = jnp.asarray(theta, dtype)
    check_last_dim("w", w, len(CONDITION_NAMES))
    check_last_dim("theta", theta, len(HEALTH_NAMES))
    batch = jnp.broadcast_shapes(w.shape[:-1], theta.shape[:-1])
    effects = (
        jnp.zeros(batch + (cycle.NUM_EFFECTS,), dtype) if effects is None else effects
    )
    effects = jnp.asarray(effects, dtype)
    check_last_dim("effects", effects, cycle.NUM_EFFECTS)
    batch = jnp.broadcast_shapes(batch, effects.shape[:-1])
    dp = design_point(d) if dp is None else dp
    if z0 is None and guess is not None:
        z0 = guessed_start(d, guess, w)
    z0 = jnp.zeros(batch + (cycle.NUM_UNKNOWNS,), dtype) if z0 is None else z0
    z0 = jnp.asarray(z0, dtype)
    flat = [
        jnp.broadcast_to(a, batch + a.shape[-1:]).reshape((-1, a.shape[-1]))
        for a in (w, theta, effects, z0)
    ]

    def one(w1, th1, ef1, z01):
        # rolled thermo loops: unrolled is ~20 us faster here but moves x by ~1e-12
        # (not bit for bit), and F's bits are the paper's (the hinted path unrolls)
        z, x, is_physical, sinfo = solver.solve_closed(
            balance_outputs, z01, (d, dp, w1, th1, ef1), solver_cfg
        )
        inside = in_envelope(envelope, w1, th1)
        closed = sinfo.residual_norm < accept
        finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(z)) & is_physical
        info = EngineInfo(closed & finite & inside, sinfo.residual_norm,
                          sinfo.iterations, inside, z)  # fmt: skip
        return x, info

    x, info = jax.vmap(one)(*flat)
    x = x.reshape(batch + x.shape[-1:])
    info = jax.tree.map(lambda a: a.reshape(batch + a.shape[1:]), info)
    return x, info


def guessed_start(d: EngineDesign, guess: GuessTable, w):
    """``[..., 9]`` the Newton start of the balance at conditions ``w`` [..., 4]:
    the table of solved balances interpolated at (corrected fan speed demand,
    Mach)."""
    pcn, _ = corrected_fan_speed_demand(d, w[..., 2])
    return jax.vmap(initial_guess, (None, 0, 0))(
        guess, pcn.reshape(-1), w[..., 1].reshape(-1)
    ).reshape(w.shape[:-1] + (cycle.NUM_UNKNOWNS,))


def check_last_dim(name, a, n):
    if a.ndim == 0 or a.shape[-1] != n:
        raise ValueError(f"{name} must have shape [..., {n}], got {tuple(a.shape)}")


def check_inputs(env: Envelope, w: np.ndarray, theta: np.ndarray) -> None:
    """Raise a ``ValueError`` naming the first field outside the model's envelope."""
    if w.ndim == 0 or w.shape[-1] != 4:
        raise ValueError(f"w must have shape [..., 4] {CONDITION_NAMES}, got {w.shape}")
    if theta.ndim == 0 or theta.shape[-1] != 10:
        raise ValueError(
            f"theta must have shape [..., 10] {HEALTH_NAMES}, got {theta.shape}"
        )
    dev = w[..., 3] - np.asarray(isa_total_temperature(w[..., 0], w[..., 1]))
    checks = [
        ("alt", w[..., 0], env.alt_ft, "ft"),
        ("Mach", w[..., 1], env.mach, "-"),
        ("TRA", w[..., 2], env.tra_pct, "%"),
        ("T2 - T2_ISA(alt, Mach)", dev, env.t2_dev_r, "degR"),
    ]
    for name, v, (lo, hi), unit in checks:
        bad = ~((v >= lo) & (v <= hi))
        if bad.any():
            i = tuple(int(k) for k in np.argwhere(bad)[0])
            raise ValueError(
                f"w[..., '{name}'] = {v[i]!r} {unit} at index {i} is outside the valid "
                f"range [{lo}, {hi}] {unit} (NaN is never valid)"
            )
    lo, hi = env.theta_bounds()
    bad = ~((theta >= lo) & (theta <= hi))
    if bad.any():
        pos = tuple(int(k) for k in np.argwhere(bad)[0])
        j = pos[-1]
        raise ValueError(
            f"theta[..., '{HEALTH_NAMES[j]}'] = {theta[pos]!r} at index {pos[:-1]} is "
            f"outside the valid range [{lo[j]}, {hi[j]}] (NaN is never valid)"
        )
