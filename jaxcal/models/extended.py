"""An extended model: a base model with added parameters, stored as JSON.

The diagnosis (:mod:`jaxcal.diagnosis.extended`) closes the loop by declaring the
effects it found; this module builds that model from a base :class:`~jaxcal.model.Model`
and a list of :class:`Added` parameters, and reads it back from an
``extended_model.json`` file, so that ``jaxcal.models.load("…/extended_model.json")``
and ``model=`` on every command line accept it. Each added parameter enters through
one channel: a base ``parameter`` (undeclared until now), a registered ``effect``
input, a ``condition`` offset (the model sees ``w + offset``), or the measurement
layer, ``additive`` (``x + a``) or ``multiplicative`` (``x (1 + m)``) on one output.
The base model's other parameters are held at their nominal values. Loading the file
loads the base model; a base given as a Python file runs that file's code, as loading
a pickle does: load only files you trust.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxcal.model import Model, Parameter

FORMAT = "jaxcal.extended_model/1"


class Added(NamedTuple):
    """One parameter of the extension."""

    name: str  # the extended model's parameter name
    channel: str  # parameter, effect, condition, additive or multiplicative
    target: str  # the base model's parameter, effect, condition or output
    nominal: float
    low: float
    high: float
    unit: str
    scale: float  # natural step


def build_extended(
    base: Model, declared: Sequence[str], added: Sequence[Added], name: str = ""
) -> Model:
    """``base`` with parameters ``declared + added`` (the rest held at nominal)."""
    declared = tuple(declared)
    base_idx = np.asarray(base.parameter_index(declared), int)
    nominal = np.asarray(base.nominal, np.float64)
    p_decl = len(declared)
    param_extra = [a for a in added if a.channel == "parameter"]
    extra_idx = np.asarray(
        base.parameter_index([a.target for a in param_extra]), int
    ).reshape(-1)
    n_eff = len(base.effects)
    eff_names = [e.name for e in base.effects]
    pos = {a.name: p_decl + k for k, a in enumerate(added)}

    def split(theta):
        full = jnp.asarray(nominal, theta.dtype).at[base_idx].set(theta[:p_decl])
        if extra_idx.size:
            full = full.at[extra_idx].set(
                jnp.stack([theta[pos[a.name]] for a in param_extra])
            )
        effects = jnp.zeros(n_eff, theta.dtype)
        w_off = jnp.zeros(len(base.conditions), theta.dtype)
        add = jnp.zeros(len(base.outputs), theta.dtype)
        mult = jnp.zeros(len(base.outputs), theta.dtype)
        for a in added:
            v = theta[pos[a.name]]
            if a.channel == "effect":
                effects = effects.at[eff_names.index(a.target)].set(v)
            elif a.channel == "condition":
                w_off = w_off.at[base.condition_names.index(a.target)].set(v)
            elif a.channel == "additive":
                add = add.at[base.output_index([a.target])[0]].set(v)
            elif a.channel == "multiplicative":
                mult = mult.at[base.output_index([a.target])[0]].set(v)
        return full, effects, w_off, add, mult

    parameters = [base.parameters[i] for i in base_idx] + [
        Parameter(a.name, a.nominal, a.low, a.high, a.unit) for a in added
    ]
    scales = {**dict(base.diagnosis.scales or {}), **{a.name: a.scale for a in added}}
    hints = base.diagnosis._replace(scales=scales)
    name = name or f"{base.name} (extended: {', '.join(a.name for a in added)})"
    common = dict(
        conditions=base.conditions, parameters=parameters, outputs=base.outputs,
        name=name, condition_range=base.condition_range, input_check=base.input_check,
        x64=base.x64,
    )  # fmt: skip
    if not base.is_stateful:

        def fn(w, theta):
            full, effects, w_off, add, mult = split(theta)
            if n_eff:
                x, info = base.evaluate_effects(w + w_off, full, effects)
            else:
                x, info = base.evaluate(w + w_off, full)
            return x * (1.0 + mult) + add, info

        return Model.from_function(fn, diagnosis=hints, **common)

    def step(z, w, theta):
        full, _, w_off, add, mult = split(theta)
        z_next, x, info = base.step(z, w + w_off, full)
        return z_next, x * (1.0 + mult) + add, info

    def init(w0, theta):
        full, _, w_off, _, _ = split(theta)
        return base.init_state(w0 + w_off, full)

    model = Model.from_step(step, init_state=init, states=base.states, **common)
    return dataclasses.replace(model, diagnosis=hints)


def resolve_base(spec: dict, path: str) -> str:
    """The base model spec of an extension read from ``path`` (a relative ``.py``
    base is resolved against the file's folder)."""
    base = str(spec["base"])
    if ":" in base and base.rsplit(":", 1)[0].endswith(".py"):
        file, attr = base.rsplit(":", 1)
        if not os.path.isabs(file):
            file = os.path.join(os.path.dirname(os.path.abspath(path)), file)
        base = f"{file}:{attr}"
    return base


def load_extended(path: str) -> Model:
    """The model of an ``extended_model.json`` (a relative ``.py`` base is resolved
    against the file's folder)."""
    from jaxcal.models import load

    try:
        with open(path) as f:
            spec = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(
            f"{path}: not a readable extended-model file ({err})"
        ) from None
    if not isinstance(spec, dict) or spec.get("format") != FORMAT:
        raise ValueError(f"{path}: not an extended model (expected format {FORMAT!r})")
    base = resolve_base(spec, path)
    try:
        added = [Added(**a) for a in spec["added"]]
    except (KeyError, TypeError) as err:
        raise ValueError(f"{path}: bad 'added' entry ({err})") from None
    return build_extended(load(base), spec["declared"], added)
