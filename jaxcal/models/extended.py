"""An extended model: a base model with added parameters, stored as JSON.

The diagnosis (:mod:`jaxcal.diagnosis.report.extended`) closes the loop by declaring the
effects it found; this module builds that model from a base :class:`~jaxcal.model.Model`
and a list of :class:`Added` parameters, and reads it back from an
``extended_model.json`` file, so that ``jaxcal.models.load("…/extended_model.json")``
and ``model=`` on every command line accept it. Each added parameter enters through
one channel: a base ``parameter`` (undeclared until now), a registered ``effect``
input, a ``condition`` offset (the model sees ``w + offset``), or the measurement
layer, ``additive`` (``x + a``) or ``multiplicative`` (``x (1 + m)``) on one output.
The base model's other parameters are held at their nominal values.

An effect the diagnosis found in some units only is added for those units: its
:class:`Added` ``units`` lists the carriers' ids (as in the data's ``unit`` column;
``None``, or no ``units`` key in an older file: every unit). The model's function is
the same in every unit; the carriers go into its hints (``diagnosis.carriers``,
:class:`~jaxcal.model.DiagnosisHints`), and :func:`jaxcal.calibrate` calibrates the
parameter in the carriers only and holds it at its nominal value (0: no effect) with
std 0 in every other unit (:mod:`jaxcal.calibrators.front.carriers`), so that a clean
unit is calibrated as with the base model. The JSON is data;
its base is code when it names a ``.py`` file or a module, which runs only with the
user's consent (:mod:`jaxcal.trust`, ``docs/trust.md``): ``trust_code=True``, or the
same file (same bytes) named by the user in this process. A base that is a registered
name loads without asking.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxcal import trust
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
    units: tuple[int, ...] | None = None  # the carriers' unit ids (None: every unit)


def _carrier_ids(a: Added, where: str) -> tuple[int, ...] | None:
    """``a.units`` as sorted unit ids (``None``: every unit).

    Raises:
        ValueError: naming ``where`` and the parameter when it is not a list of
            integer unit ids.
    """
    if a.units is None:
        return None
    try:
        ids = [int(u) for u in a.units if float(u) == int(u)]
    except (TypeError, ValueError):
        ids = None
    if ids is None or isinstance(a.units, str) or len(ids) != len(a.units):
        raise ValueError(
            f"{where}: added parameter {a.name!r}: 'units' must be a list of integer "
            f"unit ids (the carriers; null: every unit), got {a.units!r}"
        )
    return tuple(sorted(set(ids)))


def build_extended(
    base: Model, declared: Sequence[str], added: Sequence[Added], name: str = ""
) -> Model:
    """``base`` with parameters ``declared + added`` (the rest held at nominal; an
    added parameter with ``units`` calibrated in those units only: module doc)."""
    declared = tuple(declared)
    added = [a._replace(units=_carrier_ids(a, "build_extended")) for a in added]
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
    carriers = {
        **{k: v for k, v in (base.diagnosis.carriers or {}).items() if k in declared},
        **{a.name: a.units for a in added if a.units is not None},
    }
    hints = base.diagnosis._replace(scales=scales, carriers=carriers or None)
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

        model = Model.from_function(fn, diagnosis=hints, **common)
        return dataclasses.replace(model, file_readers=base.file_readers)

    def step(z, w, theta):
        full, _, w_off, add, mult = split(theta)
        z_next, x, info = base.step(z, w + w_off, full)
        return z_next, x * (1.0 + mult) + add, info

    def init(w0, theta):
        full, _, w_off, _, _ = split(theta)
        return base.init_state(w0 + w_off, full)

    model = Model.from_step(step, init_state=init, states=base.states, **common)
    return dataclasses.replace(model, diagnosis=hints, file_readers=base.file_readers)


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


def check_base_consent(base: str, path: str, trust_code: bool, registered) -> None:
    """Refuse a ``.py`` or module base the user did not consent to run
    (:func:`jaxcal.trust.require_consent`); a name of ``registered`` passes."""
    where, sep, attr = base.rpartition(":")
    if base in registered or not sep:
        return
    what = f"{path}: its base {base!r}"
    if where.endswith(".py") or os.sep in where:
        try:
            with open(where, "rb") as f:
                content = f.read()
        except OSError as err:
            raise ValueError(f"{what} cannot be read ({err})") from None
        trust.require_consent(content, attr, what, trust_code)
        return
    if trust_code:
        return
    # a module: only one the user named (and so imported) before; never a search
    # of sys.path on the file's say-so
    module = sys.modules.get(where)
    origin = getattr(module, "__file__", None) if module is not None else None
    content = b""
    if origin and os.path.isfile(origin):
        with open(origin, "rb") as f:
            content = f.read()
    trust.require_consent(content, base, what, trust_code)


def read_extended(path: str) -> tuple[str, list[str], list[Added]]:
    """``(base spec, declared, added)`` of an ``extended_model.json`` (a relative
    ``.py`` base resolved against the file's folder), nothing loaded or run: the
    models' loader (:func:`jaxcal.models.load`) loads the base after the consent
    check (:func:`check_base_consent`) and builds the model (:func:`build_extended`).

    Raises:
        ValueError: the file is not an extended model.
    """
    try:
        with open(path) as f:
            spec = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(
            f"{path}: not a readable extended-model file ({err})"
        ) from None
    if not isinstance(spec, dict) or spec.get("format") != FORMAT:
        raise ValueError(f"{path}: not an extended model (expected format {FORMAT!r})")
    try:
        base = resolve_base(spec, path)
        added = [Added(**a) for a in spec["added"]]
        declared = list(spec["declared"])
    except (KeyError, TypeError) as err:
        raise ValueError(
            f"{path}: bad extended model, field {err} missing or malformed (expected "
            "'base', 'declared' and 'added' as written by jaxcal.diagnose)"
        ) from None
    added = [a._replace(units=_carrier_ids(a, path)) for a in added]
    return base, declared, added
