"""The public engine model: ``load_engine(name).evaluate(w, theta) -> (x, info)``.

``evaluate`` is pure: it works under ``jax.jit``, ``jax.vmap`` (it also accepts any
leading batch shape itself) and ``jax.jacfwd`` / ``jax.grad`` with respect to ``w``,
``theta`` and the design constants, the latter through the implicit-function theorem at
the Newton solution (:mod:`jaxcal.models.turbofan.physics.solver`). The solve runs in
float64 when JAX has x64 enabled (:func:`jaxcal.precision.enable_x64`, done by every
jaxcal entry point); in float32 the tolerances are relaxed accordingly and
``info.converged`` says whether they were met.

``info.converged`` is False whenever the balance did not close, any output is not
finite, or the inputs lie outside the model's envelope (:class:`Envelope`): a NaN in
``x`` never comes without that flag. :meth:`Engine.evaluate_checked` is the host-side
entry point that raises a clear error naming the offending field and its valid range.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxcal.models.turbofan.physics import cycle, solver
from jaxcal.models.turbofan.physics.configs import load_design, stored_guess_table
from jaxcal.models.turbofan.physics.constants import (
    CONDITION_NAMES,
    CONDITION_UNITS,
    HEALTH_NAMES,
    SENSOR_NAMES,
)
from jaxcal.models.turbofan.physics.design import (
    DesignPoint,
    EngineDesign,
    design_point,
)
from jaxcal.models.turbofan.physics.evaluation import (
    Envelope,
    check_inputs,
    evaluate_design,
    guessed_start,
)
from jaxcal.models.turbofan.physics.guess import GuessTable, build_guess_table
from jaxcal.models.turbofan.physics.warm_start import evaluate_hinted
from jaxcal.precision import float_dtype


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

    def evaluate_from(self, w, theta, effects, z0):
        """:meth:`evaluate` started from ``z0`` [..., 9] (``info.z`` of a nearby
        point: the same balance closed in fewer Newton iterations, one when ``z0``
        solves it already); a sample whose ``z0`` is not finite starts from the
        guess table as :meth:`evaluate` does. Differentiable in ``theta`` and
        ``effects`` as :meth:`evaluate` (not through ``z0``)."""
        w, z0 = (jnp.asarray(a, float_dtype()) for a in (w, z0))
        known = jnp.all(jnp.isfinite(z0), axis=-1, keepdims=True)
        z0 = jnp.where(known, z0, guessed_start(self.design, self.guess, w))
        return self.evaluate(w, theta, effects=effects, z0=z0)

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

    With ``fitted`` (default) the stored fit of the design constants and its Newton
    start table are used; otherwise the nominal constants (the table is then built
    here).
    """
    design = load_design(name, fitted=fitted)
    table = stored_guess_table(name) if fitted else None
    if table is None:
        return make_engine(design, ENVELOPES[name])
    return Engine(
        design=design, guess=table, envelope=ENVELOPES[name],
        point=_design_point(design),
    )  # fmt: skip
