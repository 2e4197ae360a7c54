"""The effect library of the diagnosis and the extended model it needs.

Every candidate effect is a parametric extension phi of a static model F (paper eq.
cal: ``x = g(F(w, theta), w)``) with a known meaning, read from the
:class:`~jaxcal.model.Model`:

* ``parameter[<name>]``: an undeclared model parameter, fitted per unit as a smooth
  function of time like the declared ones (something that drifts which calibration
  does not move);
* ``<effect>``: the model's own registered extension inputs (``model.effects`` /
  ``model.effect_fn``; the turbofan's bleed, power offtake, nozzle areas, inlet
  recovery, T2 offset), constant over the data;
* ``condition_offset[<w>]``: a logged condition off by a constant (the model sees
  ``w + offset``), for the conditions the model allows
  (``DiagnosisHints.offset_conditions``);
* ``sensor_bias[<s>]``, ``sensor_gain[<s>]``, ``sensor_drift[<s>]``,
  ``sensor_gain_drift[<s>]``: the measurement layer
  ``y_s = x_s (1 + gain_s + gain_drift_s tau) + bias_s + drift_s tau`` with ``tau`` the
  time since the unit's first row, per 100 time steps (:func:`sensor_layer`): a sensor
  drifts in the field either additively (an offset growing in time) or
  multiplicatively (a gain growing in time, e.g. a fuel-flow meter's calibration).

An inlet-temperature error comes in two forms on an engine whose controller schedules
on the inlet temperature: the engine's registered ``t2_offset`` (the engine is hotter
than the log, the controller sees the logged value) and ``condition_offset[T2]`` (the
log alone is wrong: engine and controller both see the true inlet). A model enables the
second through ``DiagnosisHints.offset_conditions``.

The extended model is ``y = sensor_layer(F(w + offset, theta, effects), layer, tau)``.
Its signatures ``dy/dphi`` are never tabulated: :func:`linearize` returns ``y`` with
``jax.jacfwd`` with respect to every model parameter, the registered effects and (when
the model allows condition offsets) the conditions, and ``jax.jvp`` of the measurement
layer with respect to its per-sensor parameters. One jitted function with a fixed chunk
of :data:`CHUNK_ROWS` rows serves every data set of a model (the model is a static
argument, hashed by identity), so an expensive model compiles once per process.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.model import Model

CHUNK_ROWS = 256  # the one row-chunk shape the linearisation is compiled for
LAYER_NAMES = ("sensor_bias", "sensor_gain", "sensor_drift", "sensor_gain_drift")
FAMILIES = ("parameter", "effect", "condition_offset", *LAYER_NAMES)
TAU_CYCLES = 100.0  # drift unit: per 100 time steps since the unit's first row
DEFAULT_SCALE_FRACTION = 0.01  # natural step: 1 % of a parameter's bound range


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One effect of the library.

    Attributes:
        name: display name, e.g. ``"sensor_bias[T30]"``, ``"parameter[fouling]"``,
            ``"t2_offset"``.
        family: one of :data:`FAMILIES`.
        target: the parameter, registered effect, condition or output it acts on.
        per_unit: True for parameter candidates (a per-unit function of time).
        scale: physical size of one unit of the fitted coefficient.
        unit: physical unit of the effect size (the model's vocabulary).
    """

    name: str
    family: str
    target: str
    per_unit: bool
    scale: float
    unit: str

    @property
    def kind(self) -> str:
        """Study label: the effect name for registered effects, else the family."""
        return self.target if self.family == "effect" else self.family


def candidate_name(family: str, target: str) -> str:
    """Display name of a library member (``family`` as in :class:`Candidate`)."""
    return target if family == "effect" else f"{family}[{target}]"


def natural_scale(model: Model, name: str) -> float:
    """Size of one fitted unit of a parameter or registered effect ``name``:
    ``DiagnosisHints.scales`` when given, else 1 % of its bound range."""
    scales = model.diagnosis.scales or {}
    if name in scales:
        return float(scales[name])
    for p in (*model.parameters, *model.effects):
        if p.name == name:
            return DEFAULT_SCALE_FRACTION * (p.high - p.low)
    raise ValueError(f"model {model.name!r} has no parameter or effect {name!r}")


def offset_conditions(model: Model) -> tuple[str, ...]:
    """The conditions that may carry a constant offset (generic candidates)."""
    allowed = model.diagnosis.offset_conditions
    return model.condition_names if allowed is None else tuple(allowed)


def build_library(
    model: Model,
    declared: Sequence[str],
    sensor_names: Sequence[str],
    noise_std: np.ndarray,
    sensor_mean_abs: np.ndarray,
    condition_scale: np.ndarray | None = None,
    *,
    families: Sequence[str] | None = None,
) -> tuple[Candidate, ...]:
    """All candidate effects for a data set (the undeclared parameters first).

    Args:
        model: the model (its parameters, effects, conditions and units).
        declared: declared (calibrated) parameters; they are not candidates.
        sensor_names: the ``S`` outputs of the residual.
        noise_std: ``[S]`` noise std per output (sets the sensor-layer scales).
        sensor_mean_abs: ``[S]`` mean ``|x_s|`` (scale of a gain).
        condition_scale: ``[W]`` natural size of a condition offset (default 1).
        families: restrict to these families (``None``: all).

    Returns:
        The candidates in a fixed order: parameters, registered effects, condition
        offsets, then per output bias, gain and drift.
    """
    keep = set(families) if families is not None else None
    unknown = None if keep is None else keep - set(FAMILIES)
    if unknown:
        raise ValueError(
            f"unknown effect families {sorted(unknown)}; valid: {', '.join(FAMILIES)}"
        )

    def wanted(family):
        return keep is None or family in keep

    out = []
    if wanted("parameter"):
        for p in model.parameters:
            if p.name not in declared:
                out.append(
                    Candidate(
                        candidate_name("parameter", p.name),
                        "parameter",
                        p.name,
                        True,
                        natural_scale(model, p.name),
                        p.unit,
                    )  # fmt: skip
                )
    if wanted("effect"):
        for e in model.effects:
            scale = natural_scale(model, e.name)
            out.append(Candidate(e.name, "effect", e.name, False, scale, e.unit))
    if wanted("condition_offset"):
        for name in offset_conditions(model):
            j = model.condition_names.index(name)
            scale = 1.0 if condition_scale is None else float(condition_scale[j])
            out.append(
                Candidate(
                    candidate_name("condition_offset", name),
                    "condition_offset",
                    name,
                    False,
                    scale,
                    model.conditions[j].unit,
                )  # fmt: skip
            )
    for family in LAYER_NAMES:
        if not wanted(family):
            continue
        for s, name in enumerate(sensor_names):
            unit = model.unit_of(name)
            scale = {
                "sensor_bias": float(noise_std[s]),
                "sensor_gain": float(noise_std[s] / max(sensor_mean_abs[s], 1e-12)),
                "sensor_drift": float(noise_std[s]),
                "sensor_gain_drift": float(
                    noise_std[s] / max(sensor_mean_abs[s], 1e-12)
                ),
            }[family]
            unit = {
                "sensor_bias": unit,
                "sensor_gain": "-",
                "sensor_drift": f"{unit} per {TAU_CYCLES:g} cycles",
                "sensor_gain_drift": f"- per {TAU_CYCLES:g} cycles",
            }[family]
            out.append(
                Candidate(
                    candidate_name(family, name), family, name, False, scale, unit
                )
            )
    return tuple(out)


def sensor_layer(x: jax.Array, layer: jax.Array, tau: jax.Array) -> jax.Array:
    """The measurement layer ``y = x (1 + gain + gain_drift tau) + bias + drift tau``.

    Elementwise over outputs: ``y_s`` depends on ``layer[:, s]`` only, which is what
    lets :func:`linearize` read each per-output derivative from one ``jvp``.

    Args:
        x: ``[S]`` model output.
        layer: ``[4, S]`` (bias, gain, drift, gain drift) per output, zeros = no
            extension.
        tau: ``[]`` time since the unit's first row / :data:`TAU_CYCLES`.

    Returns:
        ``[S]`` measured values.
    """
    return x * (1.0 + layer[1] + layer[3] * tau) + layer[0] + layer[2] * tau


class Linearization(NamedTuple):
    """The extended model and its signatures at ``N`` rows (``E`` model outputs)."""

    y: np.ndarray  # [N, E] extended model output
    jac_theta: np.ndarray  # [N, E, P_all] dy/dtheta
    jac_effects: np.ndarray  # [N, E, n_eff] dy/d(registered effects)
    jac_w: np.ndarray  # [N, E, K] dy/d(offset of the K offset_conditions)
    jac_layer: np.ndarray  # [N, 4, E] dy_s/d(bias_s, gain_s, drift_s, gain_drift_s)
    ok: np.ndarray  # [N] bool: finite outputs and signatures, the model valid


def _linearize_row(model: Model, offset_idx, w, theta, effects, w_off, layer, tau):
    # the offset signature is taken only for the conditions that may carry one
    # (offset_idx): each extra tangent costs a pass through the model
    select = jnp.eye(len(model.conditions), dtype=w.dtype)[:, list(offset_idx)]

    def extended(th, ef, off_k):
        w_in = w + w_off + select @ off_k
        if model.effects:
            x, info = model.evaluate_effects(w_in, th, ef)
        else:
            x, info = model.evaluate(w_in, th)
        y = sensor_layer(x, layer, tau)
        return y, (y, x, info.valid)

    argnums = (0, 1, 2) if offset_idx else (0, 1)
    off_k = jnp.zeros(len(offset_idx), w.dtype)
    jacs, (y, x, valid) = jax.jacfwd(extended, argnums=argnums, has_aux=True)(
        theta, effects, off_k
    )
    j_th, j_ef = jacs[0], jacs[1]
    j_w = jacs[2] if offset_idx else jnp.zeros(y.shape + (0,), y.dtype)
    eye3 = jnp.eye(len(LAYER_NAMES), dtype=layer.dtype)
    j_layer = jax.vmap(
        lambda e: jax.jvp(
            lambda p: sensor_layer(x, p, tau),
            (layer,),
            (jnp.outer(e, jnp.ones_like(x)),),
        )[1]
    )(eye3)
    ok = valid & jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(j_th))
    ok = ok & jnp.all(jnp.isfinite(j_ef)) & jnp.all(jnp.isfinite(j_w))
    return y, j_th, j_ef, j_w, j_layer, ok


@functools.partial(jax.jit, static_argnums=(0, 1))
def _linearize_chunk(model, offset_idx, w, theta, effects, w_off, layer, tau):
    """Jitted entry point: ``[C]`` rows, one shape for every data set of a model."""
    return jax.vmap(
        functools.partial(_linearize_row, model, offset_idx),
        in_axes=(0, 0, None, None, None, 0),
    )(w, theta, effects, w_off, layer, tau)


def linearize(
    model: Model,
    w: np.ndarray,
    theta: np.ndarray,
    effects,
    layer,
    tau: np.ndarray,
    w_offset=None,
) -> Linearization:
    """Extended-model output and signatures for any number of rows.

    Rows go through :func:`_linearize_chunk` in chunks of :data:`CHUNK_ROWS`; the last
    chunk is padded with its final row so that the compiled shape never changes.

    Args:
        model: a static :class:`~jaxcal.model.Model` (float64 enabled by the caller).
        w: ``[N, W]`` logged operating conditions.
        theta: ``[N, P_all]`` all model parameters.
        effects: ``[n_eff]`` registered effects, constant over the rows.
        layer: ``[4, E]`` sensor layer (bias, gain, drift, gain drift) for all model
            outputs.
        tau: ``[N]`` drift time (time since the unit's first row / 100).
        w_offset: ``[W]`` condition offsets (default zeros); the signatures
            ``jac_w`` are computed for the conditions the model allows offsets on
            (:func:`offset_conditions`, in that order).

    Returns:
        :class:`Linearization` of numpy arrays.
    """
    if not jnp.zeros(()).dtype == jnp.float64:
        raise ValueError(
            "the diagnosis needs float64: call jax.config.update('jax_enable_x64', "
            "True) (or jaxcal.precision.enable_x64()) at the start of the program"
        )
    num_w, num_p = len(model.conditions), len(model.parameters)
    w = np.asarray(w, np.float64)
    theta = np.asarray(theta, np.float64)
    tau = np.asarray(tau, np.float64)
    n = w.shape[0]
    if w.ndim != 2 or w.shape[1] != num_w or theta.shape != (n, num_p):
        raise ValueError(
            f"linearize: expected w [N, {num_w}] and theta [N, {num_p}], got "
            f"{w.shape}, {theta.shape}"
        )
    if n == 0:
        raise ValueError("linearize: no rows")
    offset_idx = tuple(model.condition_names.index(c) for c in offset_conditions(model))
    effects = jnp.asarray(effects, jnp.float64).reshape(len(model.effects))
    w_off = jnp.zeros(num_w) if w_offset is None else jnp.asarray(w_offset)
    layer = jnp.asarray(layer, jnp.float64)
    if layer.shape != (len(LAYER_NAMES), len(model.outputs)):
        raise ValueError(
            f"linearize: layer must be [{len(LAYER_NAMES)}, {len(model.outputs)}] "
            f"({', '.join(LAYER_NAMES)} per model output), got {layer.shape}"
        )
    parts = []
    for start in range(0, n, CHUNK_ROWS):
        stop = min(start + CHUNK_ROWS, n)
        pad = CHUNK_ROWS - (stop - start)
        take = np.concatenate([np.arange(start, stop), np.full(pad, stop - 1)])
        out = _linearize_chunk(
            model,
            offset_idx,
            jnp.asarray(w[take]),
            jnp.asarray(theta[take]),
            effects,
            w_off,
            layer,
            jnp.asarray(tau[take]),
        )
        parts.append([np.asarray(a)[: stop - start] for a in out])
    y, j_th, j_ef, j_w, j_layer, ok = (
        np.concatenate(p, axis=0) for p in zip(*parts, strict=True)
    )
    return Linearization(y, j_th, j_ef, j_w, j_layer, ok.astype(bool))
