"""What a :class:`jaxcal.model.Model`'s functions must return, checked when JAX
traces them.

A model declares its outputs ``[S]`` and hidden states ``[Z]`` by name; its
functions must return exactly that: ``x`` a ``[S]`` real floating array in the
declared order, a state a ``[Z]`` one, a validity flag a ``[]`` bool. Anything else
would be read wrongly without a word (JAX clamps an out-of-range index, so a model
returning 2 of its 3 outputs would have one output compared with another), or fail
deep inside a calibrator with an error that names nothing of the user's.

The checks look only at shapes and dtypes, which JAX knows while it traces: under
``jax.jit`` they run once per compilation, when the model is first evaluated, and
cost nothing per sample. (A probe evaluation at construction would trace the model
once more: tens of seconds for the turbofan's Newton solver, and a wasted trace for
every model only loaded to be asked a question.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp


class ModelContractError(ValueError):
    """A model's function returned something other than what the model declares."""


def checked_vector(
    value: Any, names: Sequence[str], *, model: str, call: str, kind: str
) -> Any:
    """``value`` as returned, after checking it is a ``[len(names)]`` real float
    array (one entry per declared ``kind`` in ``names``).

    Raises:
        ModelContractError: naming the model, the call, the declared names and what
            came back (a list, a scalar, another shape, an integer or complex dtype).
    """
    n = len(names)
    head = f"model {model!r}: {call} returned"
    want = f"expected a [{n}] float array, one value per declared {kind} {list(names)}"
    if isinstance(value, (list, tuple)):
        raise ModelContractError(
            f"{head} a Python {type(value).__name__} of {len(value)} items; {want} "
            "(return jnp.stack([...]))"
        )
    if isinstance(value, (bool, int, float, complex)):
        value = jnp.asarray(value)
    if not (hasattr(value, "shape") and hasattr(value, "dtype")):
        raise ModelContractError(f"{head} a {type(value).__name__}; {want}")
    shape = tuple(value.shape)
    if shape != (n,):
        got = "a scalar (shape ())" if shape == () else f"shape {shape}"
        if len(shape) == 1:
            got = f"{shape[0]} values for the {n} declared {kind}s"
            fix = (
                "the extra values are not dropped: declare them or return only the "
                "declared ones"
                if shape[0] > n
                else f"return every declared {kind} in order"
            )
        elif math.prod(shape) == n:
            fix = "flatten it (x.reshape(-1)) if that is the declared order"
        else:
            fix = f"return one value per declared {kind}"
        raise ModelContractError(f"{head} {got}; {want}: {fix}")
    if not jnp.issubdtype(value.dtype, jnp.floating):
        why = (
            "complex values have no order and no real residual"
            if jnp.issubdtype(value.dtype, jnp.complexfloating)
            else f"an integer or bool {kind} has no gradient, so calibration would "
            "not move"
        )
        raise ModelContractError(
            f"{head} {value.dtype} values; {want} ({why}; return float values, "
            "e.g. x.astype(float))"
        )
    return value


def checked_valid(valid: Any, *, model: str, call: str) -> Any:
    """``valid`` as returned (``None``, a :class:`~jaxcal.model_spec.ModelInfo` or a
    ``[]`` bool), after checking a flag is one per sample, not one per output."""
    flag = getattr(valid, "valid", valid)
    if flag is not None and jnp.shape(flag) != ():
        raise ModelContractError(
            f"model {model!r}: {call} returned a validity flag of shape "
            f"{jnp.shape(flag)}; expected a [] bool (one flag per sample) or a "
            "ModelInfo"
        )
    return valid


def checked_output(model, x: Any, valid: Any, call: str) -> tuple[Any, Any]:
    """``(x, valid)`` of one evaluation of ``model`` (a :class:`~jaxcal.model.Model`)
    after the checks of :func:`checked_vector` and :func:`checked_valid`."""
    x = checked_vector(
        x, model.output_names, model=model.name, call=call, kind="output"
    )
    return x, checked_valid(valid, model=model.name, call=call)


def checked_state(model, state: Any, call: str) -> Any:
    """A hidden state of ``model`` after the checks of :func:`checked_vector` (a
    static model's empty state passes through)."""
    if not model.is_stateful:
        return state
    return checked_vector(
        state, model.state_names, model=model.name, call=call, kind="state"
    )


def split_output(
    out: Any, names: Sequence[str], *, model: str, call: str
) -> tuple[Any, Any]:
    """A static function's result ``x`` or ``(x, valid)`` -> ``(x, valid or None)``
    (``names``: the declared outputs, for the error)."""
    if not isinstance(out, tuple):
        return out, None
    if len(out) != 2:
        raise ModelContractError(
            f"model {model!r}: {call} returned a tuple of {len(out)} items; expected "
            f"x (a [{len(names)}] float array, one value per declared output "
            f"{list(names)}) or (x, valid); a tuple is read as (x, valid): return "
            "jnp.stack([...]) for the outputs"
        )
    return out


def split_step(out: Any, *, model: str, call: str) -> tuple[Any, Any, Any]:
    """A step function's result ``(next_state, x)`` or ``(next_state, x, valid)`` ->
    ``(next_state, x, valid or None)``."""
    if not isinstance(out, (tuple, list)) or len(out) not in (2, 3):
        got = (
            f"a {type(out).__name__} of {len(out)} items"
            if isinstance(out, (tuple, list))
            else f"a single array of shape {jnp.shape(out)}"
            if hasattr(out, "shape")
            else f"a {type(out).__name__}"
        )
        raise ModelContractError(
            f"model {model!r}: {call} returned {got}; expected (next_state, x) or "
            "(next_state, x, valid): a model with hidden states returns its next "
            "state too"
        )
    return (out[0], out[1], out[2] if len(out) == 3 else None)
