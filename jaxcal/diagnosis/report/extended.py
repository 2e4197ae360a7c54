"""The loop closed: the extended model a diagnosis yields, as a :class:`jaxcal.Model`.

A verdict names effects the model lacks. The **extended model** declares them: its
parameters are the declared ones plus one parameter per added effect, with bounds, so
that any calibrator (the UKF, least squares, a policy trained on it) tracks the
effect's size in real time, per unit, like any other parameter:

* an undeclared model parameter (a drift or a step of it) becomes declared;
* a registered effect input or a condition offset becomes a parameter of that name
  (``<condition>_offset``);
* a sensor's additive forms (bias, drift, step) become one tracked offset
  ``<output>_offset`` and its multiplicative forms (gain, gain drift) one tracked
  relative gain ``<output>_gain_error``: a drift is an offset that grows, a step one
  that jumps, and a real-time calibrator follows either as it happens.

An effect carried by some units only (the per-unit form,
:mod:`jaxcal.diagnosis.report.units`) is added for its carriers: the units the verdict
lists (``carries``; where none passes the per-unit test, the units the screen fitted it
in), by their ids in the data (``units`` of :class:`~jaxcal.models.extended.Added`).
Every other unit is calibrated with the parameter held at zero, as with the base model:
tracked where it is absent, it would take false values and worsen the other
parameters. A fleet-wide effect is added for every unit.

The other parameters are held at their nominal values. :func:`write_extended` stores
the extension as ``extended_model.json`` beside the report; ``jaxcal.models.load``
(and so ``model=`` on every command line) accepts that file
(:mod:`jaxcal.models.extended`). Loading it loads the base model, and a base model
given as a Python file runs that file's code, as loading a pickle does: load only
reports you trust.
"""

from __future__ import annotations

import json
import os

import numpy as np

from jaxcal.diagnosis.kinds.table import natural_scale
from jaxcal.model import Model
from jaxcal.models.extended import FORMAT, Added, build_extended
from jaxcal.runs.atomic import write_atomic

BOUND_STEPS = 50.0  # a new parameter's bounds: at least this many natural steps
BOUND_FIT = 3.0  # ... and this many times the largest fitted size


def _bounds(scale: float, sizes) -> tuple[float, float]:
    sizes = np.asarray([s for s in np.ravel(sizes) if np.isfinite(s)] or [0.0])
    half = max(BOUND_STEPS * scale, BOUND_FIT * float(np.max(np.abs(sizes))))
    return -half, half


def added_parameters(res) -> list[Added]:
    """The extension of a :class:`~jaxcal.diagnosis.pipeline.DiagnosisResult`: one
    :class:`Added` per added effect (merged per channel and target; its ``units``
    the carriers of a per-unit effect, module doc)."""
    model, out = res.model, {}
    for cand, eff in zip(res.members, res.unit_effects, strict=True):
        units = carrier_ids(cand, eff, res.data.unit_ids)
        channel, target = cand.kind.channel, cand.target
        if channel == "parameter":
            p = model.parameters[model.parameter_names.index(target)]
            item = Added(target, channel, target, p.nominal, p.low, p.high, p.unit,
                         natural_scale(model, target))  # fmt: skip
        elif channel == "effect":
            p = model.effects[[e.name for e in model.effects].index(target)]
            item = Added(target, channel, target, 0.0, p.low, p.high, p.unit,
                         natural_scale(model, target))  # fmt: skip
        else:
            sizes = eff.size * (
                np.abs(np.asarray(res.data.tau).max()) if cand.kind.profile == "drift"
                else 1.0
            )  # fmt: skip
            suffix = {"condition": "offset", "additive": "offset",
                      "multiplicative": "gain_error"}[channel]  # fmt: skip
            step = cand.scale
            low, high = _bounds(step, sizes)
            unit = "-" if channel == "multiplicative" else model.unit_of(target)
            item = Added(f"{target}_{suffix}", channel, target, 0.0, low, high, unit,
                         step)  # fmt: skip
        item = item._replace(units=units)
        key = (item.channel, item.target)
        if key in out:  # a bias and a drift of one output: one tracked offset
            old = out[key]
            item = item._replace(
                low=min(old.low, item.low), high=max(old.high, item.high),
                units=None if old.units is None or units is None
                else tuple(sorted({*old.units, *units})),
            )  # fmt: skip
        out[key] = item
    return list(out.values())


def carrier_ids(cand, eff, unit_ids) -> tuple[int, ...] | None:
    """The unit ids that carry a per-unit effect (``None``: a fleet-wide one, every
    unit): those its per-unit verdict lists, else (none passed the test) those the
    screen fitted it in."""
    if not cand.per_unit:
        return None
    carries = np.asarray(eff.carries, bool)
    picked = np.flatnonzero(carries) if carries.any() else list(cand.carriers)
    ids = tuple(sorted({int(u) for u in np.asarray(unit_ids)[picked]}))
    return None if len(ids) == len(unit_ids) else ids


def extended_model(res) -> Model:
    """The extended model of a diagnosis result (module docstring)."""
    return build_extended(res.model, res.declared, added_parameters(res))


def extension_json(res, base_spec: str) -> dict:
    """The extension as stored in ``extended_model.json``."""
    return {
        "format": FORMAT,
        "base": base_spec,
        "declared": list(res.declared),
        "added": [
            {**a._asdict(), "units": None if a.units is None else list(a.units)}
            for a in added_parameters(res)
        ],
    }


def write_extended(out_dir: str, res, base_spec: str) -> str:
    """Write ``extended_model.json`` into ``out_dir`` (atomically); its path."""
    path = os.path.join(out_dir, "extended_model.json")
    spec = extension_json(res, base_spec)
    base_path = base_spec.rsplit(":", 1)[0] if ":" in base_spec else ""
    if base_path.endswith(".py") and os.path.isfile(base_path):
        # a relative path keeps the report folder movable with its model file
        rel = os.path.relpath(os.path.abspath(base_path), os.path.abspath(out_dir))
        spec["base"] = f"{rel}:{base_spec.rsplit(':', 1)[1]}"
    write_atomic(path, json.dumps(spec, indent=1) + "\n")
    return path
