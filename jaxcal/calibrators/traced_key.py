"""A user model's identity across processes: a digest of the programs it traces to.

:mod:`~jaxcal.calibrators.on_disk` keeps a compiled calibrator on disk under a key
that must name everything the program computes. For jaxcal's own models that is
jaxcal's source (``Model.origin``). A user's function has no such name: its code,
the arrays it closes over and the helpers it calls can change between processes
while its name stays. What it computes is its jaxpr, though: tracing inlines every
helper and records every captured array as a constant, so two functions with the
same jaxpr and constants give the same program. Tracing the model alone at the
shapes the calibrators call it with costs milliseconds, against the ~1 s of
tracing and lowering a whole calibrator in every new process.

The digest covers the model's functions (``step_fn``, ``init_state_fn``,
``input_check``, ``effect_fn``), each traced and, where differentiable, its
forward-mode derivative traced too: a ``jax.custom_jvp`` rule is opaque in the
primal jaxpr (printed by name only), and the calibrators use first derivatives
(least squares' Jacobian, the filter feature's). Anything whose behaviour a jaxpr
does not show refuses a digest (the model is then traced in every process, as
before): a host callback, a ``custom_vjp`` (its backward pass is a Python
function), a warm-started ``hinted_fn``, or any function that fails to trace.
"""

from __future__ import annotations

import hashlib

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jcore

from jaxcal.model import Model

_MEMO: dict = {}  # (id(model), dtype, x64) -> (model, digest): model held, id kept
_MEMO_MAX = 64


class _Opaque(Exception):
    """The jaxpr holds behaviour its text does not show."""


def traced_key(model: Model, dtype) -> str | None:
    """``"traced:<sha256>"`` naming what ``model`` computes in ``dtype``, or None
    when that cannot be read off its jaxprs (see the module docstring)."""
    key = (id(model), np.dtype(dtype).name, bool(jax.config.jax_enable_x64))
    if key not in _MEMO:
        if len(_MEMO) >= _MEMO_MAX:
            _MEMO.pop(next(iter(_MEMO)))
        _MEMO[key] = (model, _digest(model, np.dtype(dtype)))
    return _MEMO[key][1]


def _digest(model: Model, dtype: np.dtype) -> str | None:
    if model.hinted_fn is not None:
        return None
    digest = hashlib.sha256()
    digest.update(repr(_declared(model)).encode())
    for bound in model.condition_range or ():
        digest.update(np.asarray(bound, np.float64).tobytes())
    W, P, Z = len(model.conditions), len(model.parameters), len(model.states)
    w, theta, z = (jax.ShapeDtypeStruct((n,), dtype) for n in (W, P, Z))
    calls = [("step", model.step_fn, (z, w, theta))]
    calls.append(("init", model.init_state_fn, (w, theta)))
    if model.input_check is not None:
        calls.append(("check", model.input_check, (w,)))
    if model.effect_fn is not None:
        e = jax.ShapeDtypeStruct((len(model.effects),), dtype)
        calls.append(("effect", model.effect_fn, (w, theta, e)))
    try:
        for label, fn, args in calls:
            digest.update(label.encode())
            _absorb(digest, jax.make_jaxpr(fn)(*args))
            if label != "check":  # a predicate has no derivative
                _absorb(digest, jax.make_jaxpr(_tangent(fn))(*args, *args))
    except Exception:  # noqa: BLE001 - opaque or untraceable: no digest, traced again
        return None
    return "traced:" + digest.hexdigest()


def _declared(model: Model) -> tuple:
    """The model's declared names, units, bounds and flags (reprs of frozen
    dataclasses: stable across processes)."""
    return (
        model.name, model.conditions, model.parameters, model.outputs, model.states,
        model.effects, model.x64, model.diagnosis,
    )  # fmt: skip


def _tangent(fn):
    """``fn``'s forward-mode derivative along tangents given after the primals
    (float outputs only: a model's validity flag has none)."""

    def jvp(*both):
        half = len(both) // 2
        out, tangent = jax.jvp(fn, both[:half], both[half:])
        pairs = zip(jax.tree.leaves(out), jax.tree.leaves(tangent), strict=True)
        return [t for o, t in pairs if jnp.issubdtype(o.dtype, jnp.inexact)]

    return jvp


def _absorb(digest, closed) -> None:
    """Fold a closed jaxpr's text and every constant's value into ``digest``."""
    digest.update(str(closed.jaxpr).encode())
    _constants(digest, closed.consts)
    _walk(digest, closed.jaxpr)


def _constants(digest, consts) -> None:
    for c in consts:
        a = np.asarray(c)
        digest.update(f"{a.dtype}{a.shape}".encode() + a.tobytes())


def _walk(digest, jaxpr) -> None:
    """Inlined literals' values, sub-programs' constants; :class:`_Opaque` where a
    parameter holds a Python function the text shows only by name."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name.startswith("custom_vjp"):
            raise _Opaque(eqn.primitive.name)
        for var in eqn.invars:
            if isinstance(var, jcore.Literal):
                _constants(digest, [var.val])
        for name, value in eqn.params.items():
            _param(digest, eqn.primitive.name, name, value)


def _param(digest, primitive: str, name: str, value) -> None:
    if isinstance(value, jcore.ClosedJaxpr):
        _constants(digest, value.consts)
        _walk(digest, value.jaxpr)
    elif isinstance(value, jcore.Jaxpr):
        _walk(digest, value)
    elif isinstance(value, (tuple, list)):
        for v in value:
            _param(digest, primitive, name, v)
    elif callable(value) and not type(value).__module__.startswith("jax._src.mesh"):
        # a custom_jvp's rule is read through the traced derivative instead
        if not (primitive == "custom_jvp_call" and name == "jvp_jaxpr_fun"):
            raise _Opaque(f"{primitive}.{name}")
