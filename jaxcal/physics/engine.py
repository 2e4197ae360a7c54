"""The public engine model: ``load_engine(name).evaluate(w, theta) -> (x, info)``.

``evaluate`` is pure: it works under ``jax.jit``, ``jax.vmap`` (it also accepts any leading
batch shape itself) and ``jax.jacfwd`` / ``jax.grad`` with respect to ``w``, ``theta`` and
the design constants, the latter through the implicit-function theorem at the Newton
solution (:mod:`jaxcal.physics.solver`). The solve runs in float64 when JAX has x64
enabled (:func:`jaxcal.precision.enable_x64`, done by every jaxcal entry point); in float32
the tolerances are relaxed accordingly and ``info.converged`` says whether they were met.

``info.converged`` is False whenever the balance did not close, any output is not finite,
or the inputs lie outside the model's envelope (:class:`Envelope`): a NaN in ``x`` never
comes without that flag. :meth:`Engine.evaluate_checked` is the host-side entry point that
raises a clear error naming the offending field and its valid range.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxcal.physics import cycle, solver
from jaxcal.physics.atmosphere import isa_total_temperature
from jaxcal.physics.configs import load_design, stored_guess_table
from jaxcal.physics.constants import (
    CONDITION_NAMES,
    CONDITION_UNITS,
    HEALTH_NAMES,
    SENSOR_NAMES,
    T_STD_R,
)
from jaxcal.physics.design import (
    DesignPoint,
    EngineDesign,
    corrected_fan_speed_demand,
    design_point,
)
from jaxcal.physics.guess import GuessTable, build_guess_table, initial_guess
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


class EngineInfo(NamedTuple):
    """How the balance ended, per sample (shapes = batch shape of the call)."""

    converged: jax.Array  # bool: closed, finite and inside the envelope
    residual_norm: jax.Array  # max |normalised residual| at the solution
    iterations: jax.Array  # Newton iterations used
    in_envelope: jax.Array  # bool: inputs inside :class:`Envelope`
    z: jax.Array  # [..., 9] solution (a warm start for a nearby point)


def _sensor_vector(d: EngineDesign, st: cycle.Stations, w) -> jax.Array:
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


def _in_envelope(env: Envelope, w, theta):
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


def _physical(st: cycle.Stations):
    return (
        (st.p50 > st.p_amb)
        & (st.p15 > st.p_amb)
        & (st.t4 < T4_MAX_R)
        & (st.w_core > 0.0)
        & (st.wf > 0.0)
    )


def _residual_fn(z, params):
    d, dp, w, theta, effects = params
    return cycle.balance(d, dp, w, theta, effects, z)[0]


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
        guess: table of solved balances (:mod:`jaxcal.physics.guess`).
        envelope: validity box for ``info.in_envelope``.
        solver_cfg: Newton settings (default depends on the float precision).
        dp: precomputed design point of ``d`` (optional).

    Returns:
        (x [..., S], EngineInfo) with S = len(SENSOR_NAMES).
    """
    dtype = float_dtype()
    if solver_cfg is None:
        solver_cfg = (
            solver.SolverConfig()
            if dtype == jnp.float64
            else solver.SolverConfig(tol=2e-5, max_iter=30)
        )
    accept = max(100.0 * solver_cfg.tol, 1e-9) if dtype == jnp.float64 else 1e-4
    w = jnp.asarray(w, dtype)
    theta = jnp.asarray(theta, dtype)
    _check_last_dim("w", w, len(CONDITION_NAMES))
    _check_last_dim("theta", theta, len(HEALTH_NAMES))
    batch = jnp.broadcast_shapes(w.shape[:-1], theta.shape[:-1])
    effects = (
        jnp.zeros(batch + (cycle.NUM_EFFECTS,), dtype) if effects is None else effects
    )
    effects = jnp.asarray(effects, dtype)
    _check_last_dim("effects", effects, cycle.NUM_EFFECTS)
    batch = jnp.broadcast_shapes(batch, effects.shape[:-1])
    dp = design_point(d) if dp is None else dp
    if z0 is None and guess is not None:
        pcn, _ = corrected_fan_speed_demand(d, w[..., 2])
        z0 = jax.vmap(initial_guess, (None, 0, 0))(
            guess, pcn.reshape(-1), w[..., 1].reshape(-1)
        ).reshape(w.shape[:-1] + (cycle.NUM_UNKNOWNS,))
    z0 = jnp.zeros(batch + (cycle.NUM_UNKNOWNS,), dtype) if z0 is None else z0
    z0 = jnp.asarray(z0, dtype)
    flat = [
        jnp.broadcast_to(a, batch + a.shape[-1:]).reshape((-1, a.shape[-1]))
        for a in (w, theta, effects, z0)
    ]

    def one(w1, th1, ef1, z01):
        z, sinfo = solver.solve(_residual_fn, z01, (d, dp, w1, th1, ef1), solver_cfg)
        # rolled thermo loops: unrolled is ~20 us faster here but moves x by ~1e-12
        # (not bit for bit), and F's bits are the paper's (the hinted path unrolls)
        _, st = cycle.balance(d, dp, w1, th1, ef1, z)
        x = _sensor_vector(d, st, w1)
        inside = _in_envelope(envelope, w1, th1)
        closed = sinfo.residual_norm < accept
        finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(z)) & _physical(st)
        info = EngineInfo(closed & finite & inside, sinfo.residual_norm,
                          sinfo.iterations, inside, z)  # fmt: skip
        return x, info

    x, info = jax.vmap(one)(*flat)
    x = x.reshape(batch + x.shape[-1:])
    info = jax.tree.map(lambda a: a.reshape(batch + a.shape[1:]), info)
    return x, info


# Broyden updates per warm-started sample before falling back to the full solve: a
# flight's next sample closes in ~4-6 (experiments/cpubench/engine_latency.py).
HINT_MAX_ITER = 10


def evaluate_hinted(
    d: EngineDesign,
    w,
    theta,
    hint: solver.Hint,
    *,
    guess: GuessTable | None = None,
    envelope: Envelope = Envelope(),
    solver_cfg: solver.SolverConfig | None = None,
    dp: DesignPoint | None = None,
    max_iter: int = HINT_MAX_ITER,
):
    """One sample of :func:`evaluate_design`, warm-started along a stream.

    Why: a deployed calibrator calls F once per sample along a flight, and the cold
    solve (4 Newton iterations, each a forward-mode Jacobian) is its whole cost. From
    ``hint`` (the previous sample's solution, inverse Jacobian and sensitivity to
    (w, theta)) the start is the first-order prediction and Broyden's method
    (:func:`jaxcal.physics.solver.quasi_newton`) closes the balance to the solver's
    ``tol`` with ~6 residual evaluations and no Jacobian (the residual with unrolled
    thermo loops, cheap when not differentiated). When it does not (no hint yet, a
    jump in the conditions, a NaN hint) the sample is solved as
    :func:`evaluate_design` does from the guess table (``lax.cond``: the cold path
    runs only then; under ``vmap`` both branches run, so a batched fleet pays both),
    and the next hint carries the exact inverse Jacobian and sensitivity there. The
    outputs agree with the cold path's to the solve's tolerance (~3e-10 relative on
    Dataset #1), not bit for bit; ``info.converged`` is checked the same way (closed,
    finite, physical, inside the envelope). Not differentiable.

    Args:
        d, guess, envelope, solver_cfg, dp: as :func:`evaluate_design`.
        w: [4] one operating point; theta: [10].
        hint: :class:`jaxcal.physics.solver.Hint` (``Engine.initial_hint()`` first).
        max_iter: Broyden updates before the fallback.

    Returns:
        (x [S], EngineInfo, next hint).
    """
    dtype = float_dtype()
    cfg = solver_cfg or (
        solver.SolverConfig()
        if dtype == jnp.float64
        else solver.SolverConfig(tol=2e-5, max_iter=30)
    )
    w, theta = jnp.asarray(w, dtype), jnp.asarray(theta, dtype)
    if w.shape != (len(CONDITION_NAMES),) or theta.shape != (len(HEALTH_NAMES),):
        raise ValueError(
            f"evaluate_hinted takes one sample: w [4], theta [10], got "
            f"{tuple(w.shape)}, {tuple(theta.shape)} (vmap it for a batch)"
        )
    dp = design_point(d) if dp is None else dp
    effects = jnp.zeros((cycle.NUM_EFFECTS,), dtype)
    hint = solver.Hint(
        *(jnp.asarray(a, bool if i == 2 else dtype) for i, a in enumerate(hint))
    )
    p = jnp.concatenate([w, theta])
    usable = hint.ok
    for a in (hint.z, hint.jinv, hint.p, hint.dz_dp):
        usable = usable & jnp.all(jnp.isfinite(a))

    def balance(z):
        return cycle.balance(d, dp, w, theta, effects, z, unroll=True)

    def one(z):
        r, st = balance(z)
        return r, (_sensor_vector(d, st, w), _physical(st))

    def residual(z, _):
        # as a batch of one: XLA:CPU fuses [1]-shaped chains into fewer kernels than
        # 0-d scalars; the outputs come with every residual, so the last iterate's
        # are returned without one more balance
        return jax.tree.map(lambda a: a[0], jax.vmap(one)(z[None]))

    z0 = jnp.where(usable, solver.predicted_start(hint, p), 0.0)
    start = hint._replace(z=z0, jinv=jnp.where(usable, hint.jinv, 0.0))
    z, rmax, iters, jinv, (x, physical) = solver.quasi_newton(
        residual, start, None, cfg.tol, max_iter
    )
    inside = _in_envelope(envelope, w, theta)
    fast_ok = usable & (rmax <= cfg.tol) & jnp.all(jnp.isfinite(x)) & physical

    def fast(_):
        info = EngineInfo(inside, rmax, iters, inside, z)
        return x, info, jinv, solver.secant_sensitivity(hint, p, z)

    def cold(_):
        xc, info = evaluate_design(
            d, w, theta, guess=guess, envelope=envelope, solver_cfg=cfg, dp=dp
        )
        jac = jax.jacfwd(_residual_fn)(info.z, (d, dp, w, theta, effects))
        dr_dp = jax.jacfwd(
            lambda q: _residual_fn(info.z, (d, dp, q[:4], q[4:], effects))
        )(p)
        jinv = jnp.linalg.inv(jac)
        return xc, info, jinv, -jinv @ dr_dp

    x, info, jinv, dz_dp = jax.lax.cond(fast_ok, fast, cold, None)
    return x, info, solver.Hint(info.z, jinv, info.converged, p, dz_dp)


def _check_last_dim(name, a, n):
    if a.ndim == 0 or a.shape[-1] != n:
        raise ValueError(f"{name} must have shape [..., {n}], got {tuple(a.shape)}")


@struct.dataclass
class Engine:
    """A configured engine model (a pytree: its design constants are traced leaves)."""

    design: EngineDesign
    guess: GuessTable
    envelope: Envelope = struct.field(pytree_node=False, default=Envelope())
    # design_point(design) computed once, for the warm-started path only
    # (evaluate_hinted; None: computed per call). evaluate keeps computing it in its
    # own graph: a precomputed point differs in the last bits (z by ~5e-14) and F's
    # bits are the paper's. Stale if ``design`` is replaced without it (make_engine).
    point: DesignPoint | None = None

    condition_names = CONDITION_NAMES
    condition_units = CONDITION_UNITS
    health_names = HEALTH_NAMES
    sensor_names = SENSOR_NAMES
    effect_names = cycle.EFFECT_NAMES

    @property
    def name(self) -> str:
        return self.design.name

    def evaluate(self, w, theta, *, effects=None, z0=None):
        """Sensors x = F(w, theta) and how the balance ended.

        Args:
            w: [..., 4] (alt ft, Mach, TRA %, T2 degR).
            theta: [..., 10] health modifiers, 0 = healthy, -0.01 = 1 % loss.
            effects: optional [..., 6] model extensions (``effect_names``).
            z0: optional [..., 9] warm start (``info.z`` of a nearby point).

        Returns:
            (x [..., len(sensor_names)], EngineInfo).
        """
        return evaluate_design(
            self.design, w, theta, effects, z0, guess=self.guess,
            envelope=self.envelope,
        )  # fmt: skip

    def initial_hint(self) -> solver.Hint:
        """The warm start of a stream before its first sample (none: a full solve)."""
        size = len(CONDITION_NAMES) + len(HEALTH_NAMES)
        return solver.empty_hint(cycle.NUM_UNKNOWNS, size, float_dtype())

    def evaluate_hinted(self, w, theta, hint: solver.Hint):
        """:meth:`evaluate` of one sample, warm-started from ``hint``.

        ``hint`` is the previous call's (:meth:`initial_hint` at first); see
        :func:`evaluate_hinted`. Returns ``(x [S], EngineInfo, next hint)``.
        """
        return evaluate_hinted(
            self.design, w, theta, hint, guess=self.guess, envelope=self.envelope,
            dp=self.point,
        )  # fmt: skip

    def evaluate_checked(self, w, theta, *, effects=None):
        """Host-side evaluate that raises ``ValueError`` on bad input or no convergence.

        The error names the offending field (e.g. ``w[..., 'alt']``), the value, its
        index and the valid range.
        """
        w_np = np.asarray(w, dtype=np.float64)
        th_np = np.asarray(theta, dtype=np.float64)
        check_inputs(self.envelope, w_np, th_np)
        x, info = jax.jit(self.evaluate)(w_np, th_np, effects=effects)
        bad = ~np.asarray(info.converged)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(
                f"engine balance did not converge at batch index {idx} "
                f"(residual {float(np.asarray(info.residual_norm)[idx]):.3g}) "
                f"for w={np.broadcast_to(w_np, bad.shape + (4,))[idx].tolist()}"
            )
        return x, info


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


# Each configuration's validity box; AGTF30 is a SL-40 kft, Mach 0-0.8 engine
# (physics_facts.md 5), C-MAPSS covers SL-40 kft+ and Mach 0-0.9 (data_facts.md 1.4).
ENVELOPES = {
    "cmapss": Envelope(),
    "agtf30": Envelope(alt_ft=(-1000.0, 40000.0), mach=(0.0, 0.8)),
}


def make_engine(design: EngineDesign, envelope: Envelope | None = None) -> Engine:
    """An engine for arbitrary design constants (builds its Newton start table)."""
    point = _design_point(design)
    table = jax.jit(build_guess_table)(design, point)
    envelope = envelope or ENVELOPES.get(design.name, Envelope())
    return Engine(design=design, guess=table, envelope=envelope, point=point)


_design_point = jax.jit(design_point)


def load_engine(name: str, *, fitted: bool = True) -> Engine:
    """The engine configuration ``name`` in {"cmapss", "agtf30"}.

    With ``fitted`` (default) the stored fit of the design constants and its Newton start
    table are used; otherwise the nominal constants (the table is then built here).
    """
    design = load_design(name, fitted=fitted)
    table = stored_guess_table(name) if fitted else None
    if table is None:
        return make_engine(design, ENVELOPES[name])
    return Engine(
        design=design, guess=table, envelope=ENVELOPES[name],
        point=_design_point(design),
    )  # fmt: skip
