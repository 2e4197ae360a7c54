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
        carriers: parameter name -> the unit ids that carry it (an extended model's
            effect found in some units only, :mod:`jaxcal.models.extended`):
            ``jaxcal.calibrate`` holds it at its nominal value in every other unit.
            Default: every parameter in every unit.
    """

    scales: Mapping[str, float] | None = None
    noise_rel: Mapping[str, float] | None = None
    uninformative: Mapping[str, str] | None = None
    offset_conditions: tuple[str, ...] | None = None
    degradation_sign: Mapping[str, int] | None = None
    carriers: Mapping[str, tuple[int, ...]] | None = None


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


PARAMETER_FORMS = (
    "{name: (nominal, low, high)}, {name: (nominal, low, high, unit)}, {name: "
    "Parameter(...)} or a sequence of Parameter / (name, nominal, low, high[, unit])"
)


def _parameter(name, value, field: str) -> Parameter:
    """One parameter spec -> Parameter (``name`` None: a ``(name, nominal, low,
    high[, unit])`` row); any other form is an error listing the accepted ones. A
    bare nominal is refused: the calibrators search inside the bounds, and a
    guessed box would be a silent choice."""
    if isinstance(value, Parameter):
        return value if name is None else value._replace(name=str(name))
    is_row = isinstance(value, Sequence) and not isinstance(value, (str, bytes))
    if name is None and is_row and len(value) in (4, 5) and isinstance(value[0], str):
        name, value = value[0], tuple(value[1:])
    elif name is None or not is_row:
        want = (
            "(name, nominal, low, high[, unit]) or a Parameter"
            if name is None
            else "(nominal, low, high) or (nominal, low, high, unit): a parameter "
            "needs bounds (the calibrators search inside them)"
        )
        raise ValueError(
            f"{field}: got {value!r}; expected {want}. Accepted forms: "
            f"{PARAMETER_FORMS}"
        )
    value = tuple(value)
    if len(value) not in (3, 4):
        raise ValueError(
            f"{field} must be (nominal, low, high) or (nominal, low, high, unit), "
            f"got {value!r}"
        )
    try:
        numbers = [float(v) for v in value[:3]]
    except (TypeError, ValueError):
        raise ValueError(
            f"{field}: nominal, low and high must be numbers, got {value[:3]!r}"
        ) from None
    unit = str(value[3]) if len(value) == 4 else "-"
    return Parameter(str(name), *numbers, unit)


def as_parameters(spec, field: str = "parameters") -> tuple[Parameter, ...]:
    """``{name: (nominal, low, high[, unit])}`` or Parameters -> Parameters (see
    :data:`PARAMETER_FORMS`)."""
    if isinstance(spec, Mapping):
        items = [
            _parameter(name, value, f"{field}[{name!r}]")
            for name, value in spec.items()
        ]
    elif isinstance(spec, (str, bytes)) or not isinstance(spec, Sequence):
        raise ValueError(f"{field}: got {spec!r}; expected {PARAMETER_FORMS}")
    else:
        items = [_parameter(None, p, f"{field}[{i}]") for i, p in enumerate(spec)]
    check_names([p.name for p in items], field)
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


# Column names that tables and results give their own meaning: ``unit``, ``time``
# and ``split`` in the data (:mod:`jaxcal.data.readers`), ``valid`` and ``reason`` in
# a calibration's per-row results. A model variable of one of these names would be
# read as that column, or overwrite it, so it is refused at construction.
TABLE_COLUMNS = ("unit", "time", "split")
RESULT_COLUMNS = ("valid", "reason")
RESERVED_NAMES = TABLE_COLUMNS + RESULT_COLUMNS


# Kinds that may share a name: a state observed directly as an output is one
# quantity, and its columns differ (the output's data column ``T``, its estimate
# ``T_hat``; the state's result column ``T``; states are never data columns).
SHAREABLE = frozenset({"output", "state"})


def as_range(condition_range, num_conditions: int):
    """``(low [W], high [W])`` float64 arrays of a model's ``condition_range``
    (``None`` stays ``None``), or a ValueError saying what is wrong with it."""
    if condition_range is None:
        return None
    low, high = (np.asarray(b, np.float64) for b in condition_range)
    if low.shape != (num_conditions,) or high.shape != low.shape:
        raise ValueError(
            f"condition_range must be (low [{num_conditions}], high "
            f"[{num_conditions}]), got shapes {low.shape}, {high.shape}"
        )
    if np.any(low > high) or np.isnan(low).any() or np.isnan(high).any():
        raise ValueError("condition_range: need low <= high, no NaN")
    return low, high


def check_vocabulary(**groups: Sequence[Variable | Parameter]) -> None:
    """Each name of a model names one thing: a data column is a condition, an output
    or a true parameter, and a result column a parameter, a state or an output, so a
    name in two groups (a parameter named like a condition) or a reserved name
    (:data:`RESERVED_NAMES`) is an error naming both uses. An output and a state may
    share a name (:data:`SHAREABLE`: the output is that state), with one unit
    where both give one.

    Args:
        groups: kind (``condition=``, ``parameter=``, ...) -> its variables.
    """
    owner: dict[str, tuple[str, Variable | Parameter]] = {}
    for kind, variables in groups.items():
        for var in variables:
            name = var.name
            if name in RESERVED_NAMES:
                raise ValueError(
                    f"{kind} {name!r}: the name is reserved ({', '.join(TABLE_COLUMNS)}"
                    f" are data columns, {', '.join(RESULT_COLUMNS)} result columns); "
                    f"give the {kind} another name, e.g. {name + '_' + kind!r}"
                )
            first, first_var = owner.get(name, (None, None))
            if first is not None and {first, kind} == SHAREABLE:
                if "-" not in (first_var.unit, var.unit) and first_var.unit != var.unit:
                    raise ValueError(
                        f"{name!r} is {_a(first)} in {first_var.unit!r} and {_a(kind)}"
                        f" in {var.unit!r}: an output that is a state has its unit"
                    )
                continue
            if first is not None:
                raise ValueError(
                    f"{name!r} is both {_a(first)} and {_a(kind)}: the names of "
                    "conditions, parameters, outputs, states and effects must differ "
                    "(each names one data or result column; only an output that is "
                    "a state may share its name)"
                )
            owner[name] = (kind, var)


def _a(word: str) -> str:
    return ("an " if word[0] in "aeiou" else "a ") + word


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
