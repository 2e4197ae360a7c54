"""The effect library of the closing-the-loop diagnosis and the extended model it needs.

Every candidate effect is a parametric extension phi of the engine model F (paper eq.
cal: ``x = g(F(w, theta), w)``) with a known physical meaning:

* ``health[<name>]``: an undeclared health modifier, fitted per unit as a smooth
  function of cycle like the declared ones (a component degrading that calibration
  does not move);
* ``t2_offset``, ``customer_bleed``, ``power_offtake``, ``core_nozzle_area``,
  ``bypass_nozzle_area``, ``inlet_recovery``: the engine's own extension inputs
  (:data:`jaxcal.physics.cycle.EFFECT_NAMES`), constant over the record;
* ``sensor_bias[<s>]``, ``sensor_gain[<s>]``, ``sensor_drift[<s>]``: the measurement
  layer ``y_s = x_s (1 + gain_s) + bias_s + drift_s tau`` with ``tau`` the cycles since
  the unit's first one, per 100 cycles (:func:`sensor_layer`).

The extended model is ``y = sensor_layer(F(w, theta, effects), layer, tau)``. Its
signatures ``dy/dphi`` are never tabulated: :func:`linearize` returns ``y`` with
``jax.jacfwd`` of the extended model with respect to all 10 health modifiers and the 6
engine effects (through the engine's implicit-function gradients) and ``jax.jvp`` of the
measurement layer with respect to its per-sensor parameters. One jitted function with a
fixed chunk of :data:`CHUNK_ROWS` rows serves every record and every engine design (the
engine is a traced argument), so the expensive engine compilation happens once per
process.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.physics.constants import HEALTH_NAMES, SENSOR_NAMES, SENSOR_UNITS

CHUNK_ROWS = 256  # the one row-chunk shape the engine linearisation is compiled for
LAYER_NAMES = ("sensor_bias", "sensor_gain", "sensor_drift")
TAU_CYCLES = 100.0  # drift unit: per 100 cycles since the unit's first cycle
THETA_SCALE = 0.01  # health modifiers are fitted in units of 1 %

# Natural size of one unit of each engine effect (conditioning and reporting).
ENGINE_EFFECT_SCALE = {
    "t2_offset": (1.0, "degR"),
    "customer_bleed": (0.01, "fraction of W25"),
    "power_offtake": (100.0, "hp"),
    "core_nozzle_area": (0.01, "relative"),
    "bypass_nozzle_area": (0.01, "relative"),
    "inlet_recovery": (0.001, "P2/Pt0"),
}


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One effect of the library.

    Attributes:
        name: display name, e.g. ``"sensor_bias[T30]"``, ``"health[LPT_eff_mod]"``,
            ``"t2_offset"``.
        family: ``"health"``, ``"engine"`` or one of :data:`LAYER_NAMES`.
        target: the health modifier, engine effect or sensor it acts on.
        per_unit: True for health candidates (a per-unit function of cycle).
        scale: physical size of one unit of the fitted coefficient.
        unit: physical unit of the effect size.
    """

    name: str
    family: str
    target: str
    per_unit: bool
    scale: float
    unit: str

    @property
    def kind(self) -> str:
        """Study label: the effect name for engine effects, else the family."""
        return self.target if self.family == "engine" else self.family


def candidate_name(family: str, target: str) -> str:
    """Display name of a library member (``family`` as in :class:`Candidate`)."""
    return target if family == "engine" else f"{family}[{target}]"


def build_library(
    effect_names: Sequence[str],
    declared: Sequence[str],
    sensor_names: Sequence[str],
    noise_std: np.ndarray,
    sensor_mean_abs: np.ndarray,
    *,
    families: Sequence[str] | None = None,
) -> tuple[Candidate, ...]:
    """All candidate effects for a record (the undeclared health modifiers first).

    Args:
        effect_names: the engine's ``effect_names``.
        declared: declared (calibrated) health modifiers; they are not candidates.
        sensor_names: the ``S`` sensors of the residual.
        noise_std: ``[S]`` noise std per sensor (sets the sensor-layer scales).
        sensor_mean_abs: ``[S]`` mean ``|x_s|`` (scale of a gain).
        families: restrict to these families (``None``: all).

    Returns:
        The candidates in a fixed order: health, engine effects, then per sensor bias,
        gain and drift.
    """
    keep = set(families) if families is not None else None
    unknown = None if keep is None else keep - {"health", "engine", *LAYER_NAMES}
    if unknown:
        raise ValueError(
            f"unknown effect families {sorted(unknown)}; valid: health, engine, "
            f"{', '.join(LAYER_NAMES)}"
        )
    out = []
    if keep is None or "health" in keep:
        for h in HEALTH_NAMES:
            if h not in declared:
                out.append(
                    Candidate(
                        candidate_name("health", h), "health", h, True, THETA_SCALE, "-"
                    )
                )
    if keep is None or "engine" in keep:
        for e in effect_names:
            scale, unit = ENGINE_EFFECT_SCALE.get(e, (1.0, "-"))
            out.append(Candidate(e, "engine", e, False, scale, unit))
    for family in LAYER_NAMES:
        if keep is not None and family not in keep:
            continue
        for s, name in enumerate(sensor_names):
            unit = sensor_unit(name)
            scale = {
                "sensor_bias": float(noise_std[s]),
                "sensor_gain": float(noise_std[s] / max(sensor_mean_abs[s], 1e-12)),
                "sensor_drift": float(noise_std[s]),
            }[family]
            unit = {
                "sensor_bias": unit,
                "sensor_gain": "-",
                "sensor_drift": f"{unit} per {TAU_CYCLES:g} cycles",
            }[family]
            out.append(
                Candidate(
                    candidate_name(family, name), family, name, False, scale, unit
                )
            )
    return tuple(out)


def sensor_unit(name: str) -> str:
    """Physical unit of a sensor (``"-"`` when unknown)."""
    return SENSOR_UNITS[SENSOR_NAMES.index(name)] if name in SENSOR_NAMES else "-"


def sensor_layer(x: jax.Array, layer: jax.Array, tau: jax.Array) -> jax.Array:
    """The measurement extension ``y = x (1 + gain) + bias + drift tau``.

    Elementwise over sensors: ``y_s`` depends on ``layer[:, s]`` only, which is what
    lets :func:`linearize` read each per-sensor derivative from one ``jvp``.

    Args:
        x: ``[S]`` model output.
        layer: ``[3, S]`` (bias, gain, drift) per sensor, zeros = no extension.
        tau: ``[]`` cycles since the unit's first cycle / :data:`TAU_CYCLES`.

    Returns:
        ``[S]`` measured values.
    """
    return x * (1.0 + layer[1]) + layer[0] + layer[2] * tau


class Linearization(NamedTuple):
    """The extended model and its signatures at ``N`` rows (``E`` engine sensors)."""

    y: np.ndarray  # [N, E] extended model output
    jac_theta: np.ndarray  # [N, E, 10] dy/dtheta
    jac_effects: np.ndarray  # [N, E, 6] dy/d(engine effects)
    jac_layer: np.ndarray  # [N, 3, E] dy_s/d(bias_s, gain_s, drift_s)
    ok: np.ndarray  # [N] bool: finite outputs and signatures, balance converged


def _linearize_row(engine, w, theta, effects, layer, tau):
    def extended(th, ef):
        x, info = engine.evaluate(w, th, effects=ef)
        y = sensor_layer(x, layer, tau)
        return y, (y, x, info.converged)

    (j_th, j_ef), (y, x, converged) = jax.jacfwd(
        extended, argnums=(0, 1), has_aux=True
    )(theta, effects)
    eye3 = jnp.eye(3, dtype=layer.dtype)
    j_layer = jax.vmap(
        lambda e: jax.jvp(
            lambda p: sensor_layer(x, p, tau),
            (layer,),
            (jnp.outer(e, jnp.ones_like(x)),),
        )[1]
    )(eye3)
    ok = converged & jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(j_th))
    ok = ok & jnp.all(jnp.isfinite(j_ef))
    return y, j_th, j_ef, j_layer, ok


@jax.jit
def _linearize_chunk(engine, w, theta, effects, layer, tau):
    """Jitted entry point: ``[C]`` rows, one shape for every record (engine traced)."""
    return jax.vmap(_linearize_row, in_axes=(None, 0, 0, None, None, 0))(
        engine, w, theta, effects, layer, tau
    )


def linearize(
    engine, w: np.ndarray, theta: np.ndarray, effects, layer, tau: np.ndarray
) -> Linearization:
    """Extended-model output and signatures for any number of rows.

    Rows go through :func:`_linearize_chunk` in chunks of :data:`CHUNK_ROWS`; the last
    chunk is padded with its final row so that the compiled shape never changes.

    Args:
        engine: an engine (``evaluate(w, theta, *, effects)``, ``effect_names``).
        w: ``[N, 4]`` operating conditions.
        theta: ``[N, 10]`` health modifiers.
        effects: ``[6]`` engine effects, constant over the rows.
        layer: ``[3, E]`` sensor layer (bias, gain, drift) for all engine sensors.
        tau: ``[N]`` drift time (cycles since the unit's first cycle / 100).

    Returns:
        :class:`Linearization` of numpy arrays.
    """
    w = np.asarray(w, np.float64)
    theta = np.asarray(theta, np.float64)
    tau = np.asarray(tau, np.float64)
    n = w.shape[0]
    if w.ndim != 2 or w.shape[1] != 4 or theta.shape != (n, len(HEALTH_NAMES)):
        raise ValueError(
            f"linearize: expected w [N, 4] and theta [N, 10], got {w.shape}, "
            f"{theta.shape}"
        )
    if n == 0:
        raise ValueError("linearize: no rows")
    effects = jnp.asarray(effects, jnp.float64)
    layer = jnp.asarray(layer, jnp.float64)
    parts = []
    for start in range(0, n, CHUNK_ROWS):
        stop = min(start + CHUNK_ROWS, n)
        pad = CHUNK_ROWS - (stop - start)
        take = np.concatenate([np.arange(start, stop), np.full(pad, stop - 1)])
        out = _linearize_chunk(
            engine,
            jnp.asarray(w[take]),
            jnp.asarray(theta[take]),
            effects,
            layer,
            jnp.asarray(tau[take]),
        )
        parts.append([np.asarray(a)[: stop - start] for a in out])
    y, j_th, j_ef, j_layer, ok = (
        np.concatenate(p, axis=0) for p in zip(*parts, strict=True)
    )
    return Linearization(y, j_th, j_ef, j_layer, ok.astype(bool))
