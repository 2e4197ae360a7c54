"""A static model's per-row Jacobians over a data set, for the diagnosis's signatures
(:mod:`jaxcal.diagnosis.kinds.signatures`).

Forward derivatives along the directions a fit needs in (parameters, effects,
offset conditions), in buckets of :data:`DIRECTION_BUCKET`, one jitted function with
a fixed chunk of :data:`CHUNK_ROWS` rows per model, kept on disk across processes
(``jaxcal.calibrators.programs.on_disk``), its chunks dispatched
:data:`CHUNKS_IN_FLIGHT` ahead. A model whose solver can start from a nearby solution
(``Model.warm_fn``: the turbofan's Newton solve) takes every derivative with the same
program bucket by bucket, each bucket after the first started at the first's
solution, and each point started at the last kept point's solution on the same rows;
any other model takes every derivative in one pass. The last
:data:`LINEARIZATIONS_KEPT` points are reused (a refit starts where the fit before it
ended), a point that differs from one of them (with the derivatives wanted) on a few
rows evaluates those rows alone (:data:`PIECED_SHARE`), and only the residual's outputs
and a fit's own derivatives are kept.
"""

from __future__ import annotations

import collections
import functools
import hashlib
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.programs.compiled import cached_value
from jaxcal.calibrators.programs.on_disk import kept
from jaxcal.calibrators.programs.traced_key import traced_key
from jaxcal.diagnosis.data.sharding import evaluate_split
from jaxcal.diagnosis.kinds.table import offset_conditions
from jaxcal.diagnosis.timing import batch_progress
from jaxcal.model import Model
from jaxcal.precision import require_x64

CHUNK_ROWS = 256  # the one row-chunk shape a static model is compiled for
CHUNKS_IN_FLIGHT = 8  # row chunks dispatched before the first is read back
DIRECTION_BUCKET = 4  # a fit's derivatives are computed in groups of this many


def _directional_row(model: Model, offset_idx, w, theta, effects, w_off, basis, z0):
    """``(x, x' basis^T, ok, z)`` of one row: the output and its forward derivatives
    along the ``[D, M]`` directions ``basis`` in (parameters, effects, offset
    conditions); ``D = 0`` is the output alone. A model with a ``warm_fn`` starts
    its solver from ``z0`` (non-finite: its own start) and returns its solution
    ``z``; ``z`` is ``[0]`` without one."""
    select = jnp.eye(len(model.conditions), dtype=w.dtype)[:, list(offset_idx)]
    num_p, num_e = theta.shape[0], effects.shape[0]
    warm = model.warm_fn is not None

    def extended(u):
        th, ef, off_k = u[:num_p], u[num_p : num_p + num_e], u[num_p + num_e :]
        w_in = w + w_off + select @ off_k
        if warm:
            x, info, z = model.evaluate_from(w_in, th, ef, z0)
            return x, (info.valid, z.astype(w.dtype))
        if model.effects:
            x, info = model.evaluate_effects(w_in, th, ef)
        else:
            x, info = model.evaluate(w_in, th)
        return x, (info.valid, jnp.zeros((0,), w.dtype))

    u0 = jnp.concatenate([theta, effects, jnp.zeros(len(offset_idx), w.dtype)])
    if basis.shape[0] == 0:
        x, (valid, z) = extended(u0)
        jac = jnp.zeros(x.shape + (0,), x.dtype)
    else:

        def push(v):  # the primal is not batched: computed once for every direction
            (x, aux), (dx, _) = jax.jvp(extended, (u0,), (v,))
            return x, aux, dx

        x, (valid, z), jac = jax.vmap(push, out_axes=(None, None, 1))(basis)
    ok = valid & jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(jac))
    return x, jac, ok, z


def _linearize_program(model: Model, offset_idx: tuple, directions: int):
    """The jitted ``[C]``-row linearisation of ``model`` along ``directions``
    directions given as an argument (:func:`_directional_row`, 0: the output
    alone; one shape for every data set of a model), built once per process and
    kept on disk across processes (:func:`jaxcal.calibrators.programs.on_disk.kept`,
    under the built-in model's name or a user model's traced digest): tracing a
    model's solver costs far more than an evaluation."""

    def build():
        row = functools.partial(_directional_row, model, offset_idx)
        program = jax.jit(jax.vmap(row, in_axes=(0, 0, 0, 0, None, 0)))
        origin = model.origin or traced_key(model, np.float64)
        disk = None if origin is None else (
            "diagnosis.linearize", origin, offset_idx, CHUNK_ROWS, directions,
        )  # fmt: skip
        return kept(program, disk)

    key = ("diagnosis.linearize", model, offset_idx, directions)
    return cached_value(key, build)


class Linearization(NamedTuple):
    """A static model and its per-row Jacobians (``E`` model outputs): every
    derivative in ``jac_theta``, ``jac_effects``, ``jac_w``, or a fit's few in
    ``jac`` alone (the full arrays ``None``: a fleet's rows times every direction,
    mostly zeros, for the few a fit uses)."""

    x: np.ndarray  # [N, E]
    jac_theta: np.ndarray | None  # [N, E, P_all]
    jac_effects: np.ndarray | None  # [N, E, n_eff]
    jac_w: np.ndarray | None  # [N, E, K] offset conditions (offset_conditions order)
    ok: np.ndarray  # [N]
    outputs: tuple | None = None  # the model outputs E are (None: all of them)
    # the (channel, index) derivatives computed (None: all, in the full arrays)
    directions: frozenset | None = None
    jac: np.ndarray | None = None  # [N, E, D] those derivatives, sorted(directions)
    # [N, warm_size] the model solver's solution at each row (a model with a
    # warm_fn; NaN where the row failed): the next point's start
    z: np.ndarray | None = None

    def covers(self, keys) -> bool:
        """The derivatives along every ``(channel, index)`` of ``keys`` are here."""
        return self.directions is None or set(keys) <= self.directions

    def derivatives(self, keys) -> np.ndarray:
        """``[N, E, T]`` derivatives along ``keys``, each ``(channel, index, slot)``
        (``slot``: its position in the full array of its channel, the offset
        conditions' order for ``condition``)."""
        if self.directions is not None:
            order = sorted(self.directions)
            return np.take(self.jac, [order.index((c, i)) for c, i, _ in keys], axis=2)
        full = {"parameter": self.jac_theta, "effect": self.jac_effects,
                "condition": self.jac_w}  # fmt: skip
        return np.stack([full[c][:, :, slot] for c, _, slot in keys], axis=2)

    def arrays(self) -> tuple:
        """The arrays held (shared read-only by every caller at this point)."""
        held = (self.x, self.jac_theta, self.jac_effects, self.jac_w, self.ok, self.jac,
                self.z)  # fmt: skip
        return tuple(a for a in held if a is not None)


def linearize(
    model: Model,
    w: np.ndarray,
    theta: np.ndarray,
    effects=None,
    w_offset=None,
    *,
    outputs: Sequence[int] | None = None,
    directions=None,
    start: np.ndarray | None = None,
) -> Linearization:
    """Per-row output and Jacobians of a static model at ``N`` rows.

    Args:
        model: a static :class:`~jaxcal.model.Model` (float64 enabled).
        w: ``[N, W]`` logged conditions. theta: ``[N, P_all]``.
        effects: ``[N, n_eff]`` registered-effect inputs (default zeros).
        w_offset: ``[N, W]`` condition offsets (default zeros); the Jacobian is taken
            for the conditions the model allows offsets on
            (:func:`~jaxcal.diagnosis.kinds.table.offset_conditions`).
        outputs: the model outputs kept (indices; default all): a fleet's rows
            times every output and parameter is the memory of the diagnosis, and
            its residual uses a few outputs.
        directions: the ``(channel, index)`` derivatives wanted (channels
            ``parameter``, ``effect``, ``condition``; default all): a fit needs
            its own few, and each costs about 7 % of the model's evaluation (the
            turbofan's Newton solve is shared); those alone are returned, in
            ``jac`` (:class:`Linearization`).
        start: ``[N, warm_size]`` a model with a ``warm_fn``: its solver's start at
            each row, the ``z`` of a nearby point (NaN or ``None``: the model's
            own start).
    """
    require_x64("the diagnosis needs float64")
    w = np.asarray(w, np.float64)
    theta = np.asarray(theta, np.float64)
    n = w.shape[0]
    if w.ndim != 2 or w.shape[1] != len(model.conditions) or theta.shape != (
        n, len(model.parameters)
    ):  # fmt: skip
        raise ValueError(
            f"linearize: expected w [N, {len(model.conditions)}] and theta "
            f"[N, {len(model.parameters)}], got {w.shape}, {theta.shape}"
        )
    if n == 0:
        raise ValueError("linearize: no rows")
    effects = np.zeros((n, len(model.effects))) if effects is None else effects
    w_offset = np.zeros_like(w) if w_offset is None else w_offset
    effects = np.asarray(effects, np.float64)
    w_offset = np.asarray(w_offset, np.float64)
    offset_idx = tuple(model.condition_names.index(c) for c in offset_conditions(model))
    keep = slice(None) if outputs is None else np.asarray(outputs, int)
    basis, every = _basis(model, offset_idx, directions)
    width = basis.shape[0]  # the wanted directions, then zero rows to a bucket
    if model.warm_fn is not None and width > DIRECTION_BUCKET:
        # the solve dominates a bucket and a program with every direction is large
        # in memory: buckets of the fit's program, each after the first started at
        # the first's solution (one Newton iteration), one program for everything
        blocks = [
            basis[i : i + DIRECTION_BUCKET] for i in range(0, width, DIRECTION_BUCKET)
        ]
    else:
        blocks = [basis]
    size = basis.shape[1]
    if start is None or not model.warm_size:
        start = np.full((n, model.warm_size), np.nan)  # the model's own start
    start = np.asarray(start, np.float64)
    jac = None
    for k, block in enumerate(blocks):
        program = _linearize_program(model, offset_idx, block.shape[0])
        x_k, jac_k, ok_k, z_k = evaluate_split(
            functools.partial(
                _evaluate_rows, program, block, (w, theta, effects, w_offset, start),
                keep, n,
            ),
            n, CHUNK_ROWS,
        )  # fmt: skip
        if k == 0:
            x, ok = x_k, ok_k.astype(bool)
            start = np.where(ok[:, None], z_k, np.nan)
        else:
            ok = ok & ok_k.astype(bool)
        if len(blocks) == 1:
            jac = jac_k
        else:  # each bucket written in place: no second copy of the fleet's
            if jac is None:
                jac = np.empty(jac_k.shape[:2] + (width,), jac_k.dtype)
            lo = k * DIRECTION_BUCKET
            jac[:, :, lo : lo + block.shape[0]] = jac_k
    outputs = None if outputs is None else tuple(int(i) for i in outputs)
    z = start if model.warm_size else None
    if every:
        num_p, num_e = len(model.parameters), len(model.effects)
        return Linearization(
            x, jac[:, :, :num_p], jac[:, :, num_p : num_p + num_e],
            jac[:, :, num_p + num_e : size], ok, outputs, z=z,
        )  # fmt: skip
    slots = int(np.count_nonzero(basis.any(axis=1)))
    return Linearization(x, None, None, None, ok, outputs,
                         frozenset(directions), jac[:, :, :slots], z)  # fmt: skip


def _evaluate_rows(program, basis, arrays, keep, n, first, last):
    """``(x, jac, ok, z)`` of rows ``first .. last - 1`` in whole chunks: chunks are
    dispatched ahead and read back in order (they run on JAX's threads while the
    host waits on the oldest)."""

    out = []  # written in place as chunks are read: no second copy of the rows

    def read(start, stop, result):
        x, jac, ok, z = (np.asarray(a)[: stop - start] for a in result)
        batch_progress(stop, n, "rows")
        for k, part in enumerate((x[:, keep], jac[:, keep], ok, z)):
            if len(out) == k:
                out.append(np.empty((last - first,) + part.shape[1:], part.dtype))
            out[k][start - first : stop - first] = part

    pending = collections.deque()
    for start in range(first, last, CHUNK_ROWS):
        stop = min(start + CHUNK_ROWS, last)
        take = np.concatenate(
            [np.arange(start, stop), np.full(CHUNK_ROWS - (stop - start), stop - 1)]
        )
        w, theta, effects, w_offset, z0 = (a[take] for a in arrays)
        pending.append((start, stop, program(w, theta, effects, w_offset, basis, z0)))
        if len(pending) == CHUNKS_IN_FLIGHT:
            read(*pending.popleft())
    while pending:
        read(*pending.popleft())
    return tuple(out)


def _basis(model: Model, offset_idx: tuple, directions):
    """``(basis [D, M], every)``: the unit directions in (parameters, effects,
    offset conditions) of the wanted derivatives in their sorted order, padded with
    zero rows to a multiple of :data:`DIRECTION_BUCKET` (one compiled shape, a
    bucket, serves the fits). ``every``: all of them are wanted (``None``), or more
    than one bucket (a screen's many), or a bucket is as wide as all: every
    derivative, in input order."""
    num_p, num_e = len(model.parameters), len(model.effects)
    size = num_p + num_e + len(offset_idx)
    slots = []
    for channel, index in sorted(set(directions or ())):
        if channel == "parameter":
            slots.append(index)
        elif channel == "effect":
            slots.append(num_p + index)
        elif channel == "condition" and index in offset_idx:
            slots.append(num_p + num_e + offset_idx.index(index))
        else:
            raise ValueError(f"no derivative along {channel} {index} of {model.name!r}")
    rows = -(-len(slots) // DIRECTION_BUCKET) * DIRECTION_BUCKET
    every = directions is None or rows > DIRECTION_BUCKET or rows >= size
    if every:
        slots = list(range(size))
    rows = -(-len(slots) // DIRECTION_BUCKET) * DIRECTION_BUCKET
    basis = np.zeros((rows, size))
    basis[np.arange(len(slots)), slots] = 1.0
    return basis, every


# the last model points' linearisations: a fit starts where the one it refines
# ended, and every refit of a candidate at the declared-only solution (its terms
# at zero) evaluates the same point
LINEARIZATIONS_KEPT = 4
# An evaluation whose inputs differ from a kept one (with the derivatives wanted) on
# at most this share of the rows evaluates those rows alone and takes the others from
# it: the onset polish of a step (:func:`jaxcal.diagnosis.kinds.onsets.polish_onsets`)
# moves each carrier's onset one row at a time and evaluates the fleet at every move,
# and the refit at the moved onsets starts there.
# A row's output does not depend on the other rows of its chunk (the chunk is
# vmapped; bitwise the same).
PIECED_SHARE = 0.5
_LINEARIZED: collections.OrderedDict = collections.OrderedDict()


class _Rows(NamedTuple):
    """An ``[N, C]`` row input's bits, the columns equal on every row kept once (a
    fleet's effects and offsets are mostly zero, its parameters mostly nominal)."""

    first: np.ndarray  # [C] uint64: row 0
    varying: np.ndarray  # [V] the columns that differ from row 0 somewhere
    cols: np.ndarray  # [N, V] uint64: those columns

    @classmethod
    def of(cls, arr) -> _Rows:
        bits = _bits(arr)
        first = bits[0].copy() if len(bits) else np.zeros(bits.shape[1], np.uint64)
        varying = np.flatnonzero(np.any(bits != first, axis=0))
        return cls(first, varying, bits[:, varying])

    def changed(self, arr) -> np.ndarray:
        """``[N]`` bool: the rows where ``arr`` differs bitwise."""
        bits = _bits(arr)
        diff = bits != self.first
        diff[:, self.varying] = bits[:, self.varying] != self.cols
        return diff.any(axis=1)


def _bits(arr) -> np.ndarray:
    return np.ascontiguousarray(arr, np.float64).view(np.uint64)


class _Kept(NamedTuple):
    """A kept linearisation and the row inputs it was taken at."""

    lin: Linearization
    w_digest: str
    rows: tuple  # (theta, effects, w_offset) as _Rows


def _digest(*arrays) -> str:
    digest = hashlib.sha256()
    for arr in arrays:
        arr = np.ascontiguousarray(arr, np.float64)
        digest.update(repr(arr.shape).encode())
        digest.update(arr.tobytes())
    return digest.hexdigest()


def _changed_rows(old: tuple, new: tuple) -> np.ndarray:
    """``[N]`` bool: rows where any of the inputs ``new`` differ bitwise from the
    kept ``old`` (:class:`_Rows`)."""
    out = np.zeros(len(new[0]), bool)
    for held, arr in zip(old, new, strict=True):
        out |= held.changed(arr)
    return out


def _pieced(model, w, w_digest, outputs, rows: tuple, directions):
    """The linearisation at ``rows`` from a kept one at the same conditions with at
    least the derivatives ``directions``, only the rows whose inputs differ evaluated
    (along the kept one's directions, so that its arrays take them); ``None``: no kept
    point is near enough."""
    for (kept_model, kept_outputs, _), entry in reversed(_LINEARIZED.items()):
        base = entry.lin
        if (
            kept_model != model
            or kept_outputs != outputs
            or entry.w_digest != w_digest
            or not base.covers(directions)
        ):
            continue
        changed = _changed_rows(entry.rows, rows)
        idx = np.flatnonzero(changed)
        if idx.size > PIECED_SHARE * changed.size:
            continue
        if not idx.size:
            return base
        part = linearize(model, w[idx], *(a[idx] for a in rows), outputs=outputs,
                         directions=base.directions,
                         start=None if base.z is None else base.z[idx])  # fmt: skip
        merged = {}
        for field in ("x", "jac_theta", "jac_effects", "jac_w", "ok", "jac", "z"):
            old = getattr(base, field)
            if old is not None:
                merged[field] = old.copy()
                merged[field][idx] = getattr(part, field)
        return base._replace(**merged)
    return None


def _nearest_solution(model, w_digest) -> np.ndarray | None:
    """The model solver's solution at the rows of the latest kept point on the
    same conditions (``None``: none kept, or the model has no ``warm_fn``): a fit's
    next point is a step away, and the solver closes from it in fewer iterations."""
    for (kept_model, _, _), entry in reversed(_LINEARIZED.items()):
        if kept_model == model and entry.w_digest == w_digest:
            if entry.lin.z is not None:
                return entry.lin.z
    return None


def _point(model, data, rows) -> tuple:
    """``(key, outputs, w digest)`` of a point linearised on ``data``'s outputs at
    the row inputs ``rows`` (theta, effects, w offset): the key is their bytes."""
    outputs = tuple(int(i) for i in data.sensor_idx)
    w_digest = _digest(data.w)
    return (model, outputs, w_digest + _digest(*rows)), outputs, w_digest


def _keep(key, lin: Linearization, w_digest, rows) -> _Kept:
    """Keep ``lin`` under ``key`` as the most recent point (with the bits of
    ``rows``), the least recent one dropped past :data:`LINEARIZATIONS_KEPT`."""
    entry = _Kept(lin, w_digest, tuple(_Rows.of(a) for a in rows))
    _LINEARIZED[key] = entry
    _LINEARIZED.move_to_end(key)
    while len(_LINEARIZED) > LINEARIZATIONS_KEPT:
        _LINEARIZED.popitem(last=False)
    return entry


def remember(model, data, inputs, lin: Linearization) -> None:
    """Keep ``lin``, taken at ``inputs`` (a
    :class:`~jaxcal.diagnosis.kinds.signatures.RowInputs`) on ``data``'s outputs, as if
    just linearised there: a fit started where an earlier one ended (the next noise
    pass's refit of the same entry) finds its first evaluation here."""
    rows = (inputs.theta, inputs.effects, inputs.w_offset)
    key, outputs, w_digest = _point(model, data, rows)
    if lin.outputs == outputs:
        _keep(key, lin, w_digest, rows)


def _linearized(model, data, inputs, directions) -> Linearization:
    """:func:`linearize` at ``inputs`` (a
    :class:`~jaxcal.diagnosis.kinds.signatures.RowInputs`; the data's outputs) with at
    least the derivatives ``directions``, reused when the same point was linearised
    lately with them (the key is the inputs' bytes, not their identity), or pieced
    from a near one (:data:`PIECED_SHARE`)."""
    rows = (inputs.theta, inputs.effects, inputs.w_offset)
    key, outputs, w_digest = _point(model, data, rows)
    entry = _LINEARIZED.get(key)
    if entry is None or not entry.lin.covers(directions):
        lin = _pieced(model, data.w, w_digest, outputs, rows, directions)
        if lin is None:
            lin = linearize(model, data.w, *rows, outputs=outputs,
                            directions=directions,
                            start=_nearest_solution(model, w_digest))  # fmt: skip
        for arr in lin.arrays():
            arr.setflags(write=False)  # shared by every caller at this point
        entry = _keep(key, lin, w_digest, rows)
    _LINEARIZED.move_to_end(key)
    return entry.lin
