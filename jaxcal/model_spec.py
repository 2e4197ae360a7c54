"""The parts a :class:`jaxcal.model.Model` is declared with: named variables and
parameters (with units and bounds), the validity a model reports per call, the hints
it gives the diagnosis, and the parsing of the user's specs into them (every name
checked, every mistake a ``ValueError`` naming the field). ``jaxcal.model``
re-exports the public names.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from jaxcal.typedefs import Array


class Variable(NamedTuple):
    """A named quantity (condition, output or state) and its unit."""

    name: str
    unit: str = "-"


class Parameter(NamedTuple):
    """A calibratable parameter: nominal value, bounds and unit.

    ``nominal`` is the healthy / design value (the prior mean and the value an
    undeclared parameter is held at); ``[low, high]`` is the physically meaningful
    range (the calibrators' box).
    """

    name: str
    nominal: float
    low: float
    high: float
    unit: str = "-"


class ModelInfo(NamedTuple):
    """How one evaluation went.

    Attributes:
        valid: ``[]`` bool: the output is finite, the inputs are in range and the
            model's own solver (if any) converged.
        native: the model's own diagnostics (e.g. the engine's ``EngineInfo``), or
            ``None``.
    """

    valid: Array
    native: Any = None


class DiagnosisHints(NamedTuple):
    """What the diagnosis (:mod:`jaxcal.diagnosis`) may know about a model beyond
    its names and bounds. Every field is optional; ``None`` means the generic rule.

    Attributes:
        scales: parameter or effect name -> natural size of one unit (the diagnosis
            fits and screens in these units); default 1 % of the bound range.
        noise_rel: output name -> typical noise std relative to the mean ``|x|``
            (the start level before the noise is estimated); default 0.01.
        uninformative: output name -> why it carries no information about the
            parameters (e.g. set by a controller); left out of the residual.
        offset_conditions: conditions whose logged value may be off by a constant
            (generic candidate effects); default all, ``()`` none.
        degradation_sign: parameter name -> the sign of its usual change in service
            (-1: it falls as the system wears, e.g. an efficiency; +1: it grows, e.g.
            wear). The diagnosis flags a value of the other sign ("better than
            new"). Default: +1 when the nominal value is the lower bound, -1 when it
            is the upper bound, else unknown (not checked).
    """

    scales: Mapping[str, float] | None = None
    noise_rel: Mapping[str, float] | None = None
    uninformative: Mapping[str, str] | None = None
    offset_conditions: tuple[str, ...] | None = None
    degradation_sign: Mapping[str, int] | None = None


StepFn = Callable[[Array, Array, Array], tuple[Array, Array, Any]]
"""``step(state [Z], w [W], theta [P]) -> (next_state [Z], x [S], valid or info)``."""


def as_variables(spec, field: str) -> tuple[Variable, ...]:
    """Names, a name -> unit mapping or Variables -> a tuple of Variables."""
    if isinstance(spec, str):
        raise ValueError(
            f"{field} must be a sequence of names, got the string {spec!r}"
        )
    if isinstance(spec, Mapping):
        items = [Variable(str(k), str(v)) for k, v in spec.items()]
    else:
        items = []
        for item in spec:
            if isinstance(item, Variable):
                items.append(item)
            elif isinstance(item, str):
                items.append(Variable(item))
            elif isinstance(item, tuple) and len(item) == 2:
                items.append(Variable(str(item[0]), str(item[1])))
            else:
                raise ValueError(
                    f"{field}: expected a name, (name, unit) or Variable, got {item!r}"
                )
    check_names([v.name for v in items], field)
    return tuple(items)


def as_parameters(spec) -> tuple[Parameter, ...]:
    """``{name: (nominal, low, high[, unit])}`` or Parameters -> Parameters."""
    if isinstance(spec, Mapping):
        items = []
        for name, value in spec.items():
            if isinstance(value, Parameter):
                items.append(value._replace(name=str(name)))
                continue
            value = tuple(value)
            if len(value) not in (3, 4):
                raise ValueError(
                    f"parameters[{name!r}] must be (nominal, low, high) or "
                    f"(nominal, low, high, unit), got {value!r}"
                )
            unit = str(value[3]) if len(value) == 4 else "-"
            items.append(Parameter(str(name), *map(float, value[:3]), unit))
    else:
        items = [p if isinstance(p, Parameter) else Parameter(*p) for p in spec]
    check_names([p.name for p in items], "parameters")
    for p in items:
        if not (np.isfinite([p.nominal, p.low, p.high]).all() and p.low < p.high):
            raise ValueError(
                f"parameter {p.name!r}: need finite low < high, got [{p.low}, {p.high}]"
            )
        if not p.low <= p.nominal <= p.high:
            raise ValueError(
                f"parameter {p.name!r}: nominal {p.nominal} is outside "
                f"[{p.low}, {p.high}]"
            )
    return tuple(items)


def check_names(names: Sequence[str], field: str) -> None:
    if not names:
        raise ValueError(f"{field} must name at least one entry")
    repeated = sorted({n for n in names if list(names).count(n) > 1})
    if repeated:
        raise ValueError(f"{field}: repeated names {repeated}")


def names_to_index(names: Sequence[str], valid: Sequence[str], field: str) -> list[int]:
    """Positions of ``names`` in ``valid``; an unknown or repeated name is an error
    that lists the valid names."""
    names = [names] if isinstance(names, str) else list(names)
    unknown = [n for n in names if n not in valid]
    if unknown:
        raise ValueError(f"{field}: unknown name(s) {unknown}; valid: {list(valid)}")
    if len(set(names)) != len(names):
        raise ValueError(f"{field}: repeated names in {names}")
    return [list(valid).index(n) for n in names]
