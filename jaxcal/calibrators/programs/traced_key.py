"""A user model's identity across processes: a digest of the programs it traces to.

:mod:`~jaxcal.calibrators.programs.on_disk` keeps a compiled calibrator on disk under a
key that must name everything the program computes. For jaxcal's own models that is
jaxcal's source (``Model.origin``). A user's function has no such name: its code,
the arrays it closes over and the helpers it calls can change between processes
while its name stays. What it computes is its jaxpr, though: tracing inlines every
helper and records every captured array as a constant, so two functions with the
same jaxpr and constants give the same program. Tracing the model alone at the
shapes the calibrators call it with costs far less than tracing and lowering a whole
calibrator in every new process.

The digest covers the model's functions (``step_fn``, ``init_state_fn``,
``input_check``, ``effect_fn``, ``warm_fn``), each traced and, where differentiable, its
forward-mode derivative traced too: a ``jax.custom_jvp`` rule is opaque in the
primal jaxpr (printed by name only), and the calibrators use first derivatives
(least squares' Jacobian, the filter feature's). Anything whose behaviour a jaxpr
does not show refuses a digest (the model is then traced in every process): a host
callback, a ``custom_vjp`` (its backward pass is a Python function), a warm-started
``hinted_fn``, or any function that fails to trace.

The same digest tells a model whose function changed within a process: a function
reading a global that was reassigned traces to other constants, while the model
object, and so the in-process programs keyed by its identity, stay the same.
:func:`refresh` traces the model again (milliseconds, against a compilation of
seconds) and :func:`fingerprint` gives the result, which
:func:`~jaxcal.calibrators.programs.compiled.problem_key` holds: a changed function gets
new programs, never the old one's answers. The fingerprint reads what a jaxpr shows and
passes over what it does not (a host callback's Python function runs at every call,
so it reads its globals afresh; a ``custom_vjp``'s backward pass is not used by the
forward-mode calibrators), so every model that traces has one.
"""

from __future__ import annotations

import hashlib

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jcore

from jaxcal.model import Model

# (id(model), dtype, x64) -> (model, digest, opaque): the model held, its id kept
_MEMO: dict = {}
_MEMO_MAX = 64


def traced_key(model: Model, dtype) -> str | None:
    """``"traced:<sha256>"`` naming what ``model`` computes in ``dtype``, or None
    when that cannot be read off its jaxprs (see the module docstring)."""
    _, digest, opaque = _memo(model, dtype)
    return None if opaque else digest


def fingerprint(model: Model, dtype) -> str | None:
    """What ``model`` computes in ``dtype`` as of its last :func:`refresh` (or first
    use): its traced digest, opaque parts passed over; None when it does not trace
    (the calibrator's own trace then raises the model's error)."""
    return _memo(model, dtype)[1]


def refresh(model: Model, dtype) -> str | None:
    """Trace ``model`` again and keep the result (:func:`fingerprint`,
    :func:`traced_key`): a global its function reads may have changed since."""
    _MEMO.pop(_memo_key(model, dtype), None)
    return fingerprint(model, dtype)


def _memo_key(model: Model, dtype) -> tuple:
    return (id(model), np.dtype(dtype).name, bool(jax.config.jax_enable_x64))


def _memo(model: Model, dtype) -> tuple:
    key = _memo_key(model, dtype)
    if key not in _MEMO:
        if len(_MEMO) >= _MEMO_MAX:
            _MEMO.pop(next(iter(_MEMO)))
        _MEMO[key] = (model, *_digest(model, np.dtype(dtype)))
    return _MEMO[key]


def _digest(model: Model, dtype: np.dtype) -> tuple[str | None, bool]:
    """``(digest, opaque)``: the digest of the model's jaxprs, and whether they hold
    behaviour their text does not show (then no key on disk)."""
    opaque: list[str] = [] if model.hinted_fn is None else ["hinted_fn"]
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
    e = jax.ShapeDtypeStruct((len(model.effects),), dtype)
    if model.effect_fn is not None:
        calls.append(("effect", model.effect_fn, (w, theta, e)))
    if model.warm_fn is not None:  # the diagnosis's programs call it
        z0 = jax.ShapeDtypeStruct((model.warm_size,), dtype)
        calls.append(("warm", model.warm_fn, (w, theta, e, z0)))
    try:
        for label, fn, args in calls:
            digest.update(label.encode())
            _absorb(digest, jax.make_jaxpr(fn)(*args), opaque)
            if label != "check":  # a predicate has no derivative
                _absorb(digest, jax.make_jaxpr(_tangent(fn))(*args, *args), opaque)
    except Exception:  # noqa: BLE001 - untraceable: no digest, traced again
        return None, True
    return "traced:" + digest.hexdigest(), bool(opaque)


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
        # a Python bool (a validity flag) has no dtype: result_type reads both
        return [t for o, t in pairs if jnp.issubdtype(jnp.result_type(o), jnp.inexact)]

    return jvp


def _absorb(digest, closed, opaque: list) -> None:
    """Fold a closed jaxpr's text and every constant's value into ``digest``; what
    its text does not show is named in ``opaque``."""
    digest.update(str(closed.jaxpr).encode())
    _constants(digest, closed.consts)
    _walk(digest, closed.jaxpr, opaque)


def _constants(digest, consts) -> None:
    for c in consts:
        a = np.asarray(c)
        digest.update(f"{a.dtype}{a.shape}".encode() + a.tobytes())


def _walk(digest, jaxpr, opaque: list) -> None:
    """Inlined literals' values, sub-programs' constants; ``opaque`` names each
    parameter holding a Python function the text shows only by name."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name.startswith("custom_vjp"):
            opaque.append(eqn.primitive.name)
        for var in eqn.invars:
            if isinstance(var, jcore.Literal):
                _constants(digest, [var.val])
        for name, value in eqn.params.items():
            _param(digest, eqn.primitive.name, name, value, opaque)


def _param(digest, primitive: str, name: str, value, opaque: list) -> None:
    if isinstance(value, jcore.ClosedJaxpr):
        _constants(digest, value.consts)
        _walk(digest, value.jaxpr, opaque)
    elif isinstance(value, jcore.Jaxpr):
        _walk(digest, value, opaque)
    elif isinstance(value, (tuple, list)):
        for v in value:
            _param(digest, primitive, name, v, opaque)
    elif callable(value) and not type(value).__module__.startswith("jax._src.mesh"):
        # a custom_jvp's rule is read through the traced derivative instead
        if not (primitive == "custom_jvp_call" and name == "jvp_jaxpr_fun"):
            opaque.append(f"{primitive}.{name}")
