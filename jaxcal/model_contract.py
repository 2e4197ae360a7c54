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

The functions themselves are checked too: at construction, that each is a function
of the expected arity (:func:`check_function`; a string or a one-argument ``fn``
would otherwise fail deep inside the first calibration); when traced, JAX's errors
for what only works on concrete numbers (numpy on a traced value, a Python ``if`` or
``float()`` on theta, a ``pure_callback`` without ``vmap_method``) are translated
into one naming the model, the user's line and the fix (:func:`traced_call`).
"""

from __future__ import annotations

import inspect
import math
import os
import traceback
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


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


# ---------------------------------------------------------------- the functions


def check_functions(model: str, *given: tuple[Any, str], required: int = 1) -> None:
    """:func:`check_function` on each ``(fn, signature)``, its field the signature's
    name (``"fn(w, theta)"``: ``fn``); the first ``required`` ones must be given,
    the others are skipped where ``None`` (optional)."""
    for i, (fn, signature) in enumerate(given):
        if fn is not None or i < required:
            field = signature[: signature.index("(")]
            check_function(fn, model=model, field=field, signature=signature)


def check_function(fn: Any, *, model: str, field: str, signature: str) -> None:
    """``fn`` is a function that takes the positional arguments of ``signature``
    (e.g. ``"fn(w, theta)"``), checked at construction: a string or an array given
    in its place, or a function of another arity, would otherwise fail deep inside
    the first calibration.

    Raises:
        ModelContractError: naming the model, the field, the expected signature and
            what was given (a function whose signature Python cannot read, a
            builtin, is checked when it is called).
    """
    if not callable(fn):
        shown = repr(fn) if len(repr(fn)) <= 60 else repr(fn)[:57] + "..."
        raise ModelContractError(
            f"model {model!r}: {field} must be a function {signature}, got a "
            f"{type(fn).__name__} ({shown})"
        )
    try:
        params = inspect.signature(fn)
    except (TypeError, ValueError):  # a builtin or C function: no signature to read
        return
    inside = signature[signature.index("(") + 1 : signature.rindex(")")]
    arity = len([a for a in inside.split(",") if a.strip()])
    try:
        params.bind(*([None] * arity))
    except TypeError as err:
        name = getattr(fn, "__name__", type(fn).__name__)
        raise ModelContractError(
            f"model {model!r}: {field} is {name}{params}, which cannot be called as "
            f"{signature} ({err}); define it with exactly these {arity} positional "
            "arguments (a lambda or functools.partial fixes the others)"
        ) from None


def traced_call(fn, args: tuple, *, model: str, call: str):
    """``fn(*args)``, its JAX tracing errors translated: a user's function traced by
    ``jax.jit`` / ``vmap`` sees abstract values, and what works on concrete numbers
    (numpy, a Python ``if``, ``float()``) then fails with an error that names
    nothing of the model's. The translation names the model, the call, the user's
    line where it failed and the fix; the original error is chained (``from``).

    Raises:
        ModelContractError: numpy called on a traced value, a Python branch or
            conversion on one, a ``jax.pure_callback`` without ``vmap_method``.
    """
    try:
        return fn(*args)
    except jax.errors.TracerArrayConversionError as err:
        why = (
            "calls numpy (np.*, np.asarray, or a numpy-based library) on a traced "
            "value: the calibrators trace the model with jax.jit and vmap, where "
            "its inputs are abstract arrays; use jax.numpy (jnp.*) instead"
        )
        raise ModelContractError(_traced(model, call, why, err)) from err
    except jax.errors.ConcretizationTypeError as err:  # also bool / int conversion
        raise ModelContractError(_traced(model, call, _concrete(err), err)) from err
    except NotImplementedError as err:
        if "vmap_method" not in str(err):
            raise
        why = (
            "uses jax.pure_callback without vmap_method: the calibrators vmap the "
            "model over sigma points and units; pass vmap_method='sequential' (a "
            "Python function of one sample) or 'broadcast_all' / 'expand_dims' (one "
            "that takes a batch)"
        )
        raise ModelContractError(_traced(model, call, why, err)) from err


def _concrete(err: BaseException) -> str:
    """Why and how to fix a Python read of a traced value's number."""
    if isinstance(err, jax.errors.TracerBoolConversionError):
        what = "branches in Python on a traced input (an `if`, `while`, `and`/`or`)"
        fix = "use jnp.where(cond, a, b) or jax.lax.cond for a branch"
    elif "`float`" in str(err) or "`int`" in str(err) or "`complex`" in str(err):
        what = "converts a traced input to a Python number (float(), int())"
        fix = "keep values as arrays: x.astype(float), theta[0] rather than float(..)"
    else:
        what = "needs the value of a traced input (a shape, loop bound or index)"
        fix = "use jax.lax.fori_loop / while_loop or fixed shapes"
    return (
        f"{what}: the calibrators trace the model with jax.jit and vmap, where w and "
        f"theta are abstract arrays with no value yet; {fix}"
    )


def _traced(model: str, call: str, why: str, err: BaseException) -> str:
    where = _user_line(err)
    at = f" (at {where})" if where else ""
    return f"model {model!r}: {call} {why}{at}"


def _user_line(err: BaseException) -> str | None:
    """``"file:line: source"`` of the deepest frame of ``err``'s traceback outside
    JAX, numpy and this module: the user's line that failed to trace."""
    skip = tuple(
        os.path.dirname(m.__file__) + os.sep for m in (jax, np) if m.__file__
    ) + (__file__, os.path.join("jax", "_src"), os.path.join("jaxlib", ""))
    frames = [f for f in traceback.extract_tb(err.__traceback__)]
    users = [f for f in frames if not any(s in f.filename for s in skip)]
    if not users:
        return None
    frame = users[-1]
    code = f": {frame.line.strip()}" if frame.line else ""
    return f"{os.path.basename(frame.filename)}:{frame.lineno}{code}"


def check_warm_start(warm_fn, warm_size) -> None:
    """A model's ``warm_fn`` and ``warm_size`` (the length of its solution) go
    together (:class:`jaxcal.model.Model`)."""
    if (warm_fn is None) != (int(warm_size) == 0) or int(warm_size) < 0:
        raise ValueError(
            "warm_fn needs warm_size > 0 (the length of its z), and warm_size "
            f"a warm_fn: got {warm_fn!r} and {warm_size!r}"
        )


def warm_output(model, w, theta, e, z0):
    """``(x, valid, z)`` of ``model.warm_fn(w, theta, e, z0)``, ``x`` checked as
    :func:`checked_output` checks ``fn``'s (:meth:`jaxcal.model.Model.
    evaluate_from`)."""
    if model.warm_fn is None:
        raise ValueError(f"model {model.name!r} has no warm_fn")
    call = "warm_fn(w, theta, e, z0)"
    out = traced_call(model.warm_fn, (w, theta, e, z0), model=model.name, call=call)
    if not (isinstance(out, tuple) and len(out) == 3):
        raise ValueError(
            f"model {model.name!r}: {call} must return (x, valid, z), got "
            f"{type(out).__name__}"
        )
    x, valid = split_output(out[:2], model.output_names, model=model.name, call=call)
    x, valid = checked_output(model, x, valid, call)
    return x, valid, out[2]


def initial_state_fn(init_state, names: list[str], model: str):
    """``init_fn(w0, theta) -> state`` of a stateful model's ``init_state``: a
    function of (w0, theta), its tracing errors translated, or a fixed ``[Z]``
    array, one value per declared state (else a ModelContractError)."""
    if callable(init_state):

        def init_fn(w0, theta):
            call = "init_state(w0, theta)"
            return traced_call(init_state, (w0, theta), model=model, call=call)

        return init_fn
    init = np.asarray(init_state, dtype=np.float64)
    if init.shape != (len(names),):
        raise ModelContractError(
            f"model {model!r}: init_state has shape {init.shape}; expected "
            f"[{len(names)}], one value per declared state {names}"
        )

    def fixed(w0, theta):
        del w0
        return jnp.asarray(init, dtype=jnp.result_type(theta))

    return fixed
