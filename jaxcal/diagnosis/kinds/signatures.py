"""The extended model along a data set's rows and its signatures.

Every candidate effect enters the model through one of the channels of
:mod:`jaxcal.diagnosis.kinds.table`. The extended model of a data set is, row by row,

    y_t = x_t (1 + m_t) + a_t,   x_t = F(w_t + o_t, theta_t, e_t)      (static)
    (z_t, x_t) = step(z_{t-1}, w_t + o_t, theta_t),  z_0 = init(...) + dz0   (memory)

with per-row parameters ``theta``, registered-effect inputs ``e``, condition offsets
``o``, the measurement layer ``a`` (additive) and ``m`` (multiplicative) per output,
and, for a model with memory, an offset of each unit's initial state. A fitted
coefficient moves one channel along a *profile* in time (constant, drift, step,
spline function, on one unit or on all): a :class:`Tangent`. Its **signature** is
``dy/dcoefficient``, the column of the fit's Jacobian.

A static model's signatures are products of per-row Jacobians
(:mod:`jaxcal.diagnosis.kinds.linearization`: ``jax.jacfwd`` with
respect to all parameters, effects and offset conditions, one jitted function with a
fixed chunk of rows per model, kept on disk across processes) and
the profiles; the last few points' Jacobians are reused (a refit starts where the
fit before it ended), and only the residual's outputs are kept. A model with
memory is simulated (**output error**): each unit from its initial state, by
``lax.scan``, vmapped over units, and the signatures are forward-mode derivatives
(``jax.jvp``, vmapped over the tangents) *through the states*, so an effect acts on
the outputs the way the dynamics propagate it and no filter stands between the model
and the data (a filter's lag would otherwise be read as a fault). The measurement
layer is outside the dynamics in both cases and is applied on the host.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.diagnosis.data.sharding import evaluate_split
from jaxcal.diagnosis.kinds.linearization import Linearization, _linearized
from jaxcal.diagnosis.kinds.table import offset_conditions
from jaxcal.model import Model
from jaxcal.precision import require_x64

TIME_BUCKET = 128  # a model with memory pads its units to a multiple of this
TANGENT_BUCKET = 8  # ... and its tangents
CHANNELS = ("parameter", "effect", "condition", "state", "additive", "multiplicative")


class RowInputs(NamedTuple):
    """The extended model's inputs at every row (``N`` rows, ``U`` units)."""

    theta: np.ndarray  # [N, P_all]
    effects: np.ndarray  # [N, n_eff] registered-effect inputs
    w_offset: np.ndarray  # [N, W] condition offsets
    additive: np.ndarray  # [N, S_all] measurement layer, added
    multiplicative: np.ndarray  # [N, S_all] measurement layer, relative gain
    z0: np.ndarray  # [U, Z] offsets of the initial states (Z = 0: static)


class Tangent(NamedTuple):
    """A direction in the inputs: ``channel`` entry ``index`` (model order) moved by
    ``profile [N]`` per unit of the coefficient (a ``state`` tangent reads each
    unit's first row)."""

    channel: str
    index: int
    profile: np.ndarray


class Signatures(NamedTuple):
    """The extended model and its signatures at ``N`` rows (``S`` used outputs)."""

    y: np.ndarray  # [N, S] extended model output
    x: np.ndarray  # [N, S] model output before the measurement layer
    ok: np.ndarray  # [N] bool: finite, the model valid
    cols: np.ndarray  # [N, S, T] dy / d(tangent)
    lin: Linearization | None = None  # a static model's Jacobians (more columns)


def zero_inputs(model: Model, num_rows: int, num_units: int) -> RowInputs:
    """Nominal parameters, no effect."""
    return RowInputs(
        np.tile(model.nominal, (num_rows, 1)),
        np.zeros((num_rows, len(model.effects))),
        np.zeros((num_rows, len(model.conditions))),
        np.zeros((num_rows, len(model.outputs))),
        np.zeros((num_rows, len(model.outputs))),
        np.zeros((num_units, len(model.states))),
    )


# ---------------------------------------------------------------- static models


def _static(model, data, inputs: RowInputs, tangents, lin=None, cover=()) -> Signatures:
    used = tuple(int(i) for i in data.sensor_idx)
    offset_names = offset_conditions(model)
    directions = set()
    for tan in list(tangents) + list(cover):
        if tan.channel == "condition":
            name = model.condition_names[tan.index]
            if name not in offset_names:
                raise ValueError(f"model {model.name!r} allows no offset on {name}")
        if tan.channel in ("parameter", "effect", "condition"):
            directions.add((tan.channel, int(tan.index)))
    if lin is None or lin.outputs != used or not lin.covers(directions):
        lin = _linearized(model, data, inputs, frozenset(directions))
    x = lin.x
    gain = 1.0 + inputs.multiplicative[:, data.sensor_idx]
    y = x * gain + inputs.additive[:, data.sensor_idx]
    on_lin, keys = [], []  # the columns read from the Jacobians, in one pass
    for t, tan in enumerate(tangents):
        if tan.channel in ("parameter", "effect"):
            on_lin.append(t)
            keys.append((tan.channel, int(tan.index), tan.index))
        elif tan.channel == "condition":
            on_lin.append(t)
            k = offset_names.index(model.condition_names[tan.index])
            keys.append((tan.channel, int(tan.index), k))
    # derivative x profile x gain, in that order
    if on_lin and len(on_lin) == len(tangents):  # every column at once
        jac = lin.derivatives(keys)
        jac *= np.stack([np.asarray(tangents[t].profile, np.float64) for t in on_lin],
                        1)[:, None, :]  # fmt: skip
        jac *= gain[:, :, None]
        return Signatures(y, x, lin.ok, jac, lin)
    cols = np.zeros(x.shape + (len(tangents),))
    for t, key in zip(on_lin, keys, strict=True):  # in place: no second [N, S, T]
        col = cols[:, :, t]
        col[...] = lin.derivatives([key])[:, :, 0]
        col *= np.asarray(tangents[t].profile, np.float64)[:, None]
        col *= gain
    for t, tan in enumerate(tangents):
        if t not in on_lin:
            _layer_column(cols, t, tan, data, x)
    return Signatures(y, x, lin.ok, cols, lin)


def _layer_column(cols, t, tan: Tangent, data, x):
    """The measurement layer's signature (outside the dynamics: no propagation)."""
    if tan.channel not in ("additive", "multiplicative"):
        raise ValueError(f"unknown channel {tan.channel!r}; valid: {CHANNELS}")
    s = list(data.sensor_idx).index(tan.index)
    prof = np.asarray(tan.profile, np.float64)
    cols[:, s, t] = prof if tan.channel == "additive" else prof * x[:, s]


# ---------------------------------------------------------- models with memory


@functools.partial(jax.jit, static_argnums=(0,))
def _simulate(model, w, theta, w_off, z0, mask, d_theta, d_w, d_z0):
    """Units ``[U, T]`` simulated from their initial states, and the outputs'
    forward derivatives along ``Q`` tangents ``d_theta [Q, U, T, P]``,
    ``d_w [Q, U, T, W]``, ``d_z0 [Q, U, Z]`` (padded rows hold the state)."""

    def unit(w_u, th_u, off_u, z0_u, m_u, dth_u, dw_u, dz_u):
        def run(th, off, dz):
            z = model.init_state(w_u[0] + off[0], th[0])
            z = jnp.asarray(z, w_u.dtype).reshape(dz.shape) + dz

            def body(z, inputs):
                w_t, th_t, off_t, ok_t = inputs
                z_next, x, info = model.step(z, w_t + off_t, th_t)
                z_next = jnp.asarray(z_next, z.dtype).reshape(z.shape)
                return jnp.where(ok_t, z_next, z), (x, info.valid)

            return jax.lax.scan(body, z, (w_u, th, off, m_u))[1]

        x, valid = run(th_u, off_u, z0_u)

        def tangent(dth, dw, dz):
            primals = (th_u, off_u, z0_u)
            return jax.jvp(lambda *a: run(*a)[0], primals, (dth, dw, dz))[1]

        return x, valid, jax.vmap(tangent)(dth_u, dw_u, dz_u)

    return jax.vmap(unit, in_axes=(0, 0, 0, 0, 0, 1, 1, 1))(
        w, theta, w_off, z0, mask, d_theta, d_w, d_z0
    )


def _pad(data, arr: np.ndarray, length: int) -> np.ndarray:
    """Rows ``[N, ...]`` -> ``[U, length, ...]``, each unit repeating its last row."""
    out = []
    for u in range(data.num_units):
        a, b = data.starts[u], data.starts[u + 1]
        idx = np.minimum(np.arange(length), b - a - 1) + a
        out.append(arr[idx])
    return np.stack(out)


def _unpad(data, arr: np.ndarray) -> np.ndarray:
    """``[U, T, ...]`` -> rows ``[N, ...]``."""
    return np.concatenate(
        [arr[u, : data.starts[u + 1] - data.starts[u]] for u in range(data.num_units)]
    )


def _stateful(model, data, inputs: RowInputs, tangents) -> Signatures:
    if model.effects and np.any(inputs.effects):
        raise ValueError("registered effects of a model with memory are not supported")
    lengths = np.diff(data.starts)
    length = int(np.ceil(lengths.max() / TIME_BUCKET) * TIME_BUCKET)
    mask = np.arange(length)[None, :] < lengths[:, None]
    dyn = [t for t in tangents if t.channel in ("parameter", "condition", "state")]
    # tangent counts rounded up to a bucket: a few compiled shapes serve every fit
    num_q = int(np.ceil(max(len(dyn), 1) / TANGENT_BUCKET) * TANGENT_BUCKET)
    p_all, num_w, num_z = (
        len(model.parameters),
        len(model.conditions),
        len(model.states),
    )
    d_theta = np.zeros((num_q, data.num_rows, p_all))
    d_w = np.zeros((num_q, data.num_rows, num_w))
    d_z0 = np.zeros((num_q, data.num_units, num_z))
    first = data.starts[:-1]
    for q, tan in enumerate(dyn):
        if tan.channel == "parameter":
            d_theta[q, :, tan.index] = tan.profile
        elif tan.channel == "condition":
            d_w[q, :, tan.index] = tan.profile
        else:
            d_z0[q, :, tan.index] = np.asarray(tan.profile)[first]
    pad = functools.partial(_pad, data, length=length)
    per_unit = (pad(data.w), pad(inputs.theta), pad(inputs.w_offset), inputs.z0, mask)
    d_theta, d_w = np.stack([pad(d) for d in d_theta]), np.stack([pad(d) for d in d_w])

    def simulate(start, stop):  # units start .. stop - 1
        units = [jnp.asarray(a[start:stop]) for a in per_unit]
        tangents = [jnp.asarray(d[:, start:stop]) for d in (d_theta, d_w, d_z0)]
        return tuple(np.asarray(a) for a in _simulate(model, *units, *tangents))

    # on a cluster, each process simulates its block of units (.sharding)
    x, valid, dx = evaluate_split(simulate, data.num_units)
    used = data.sensor_idx
    x = _unpad(data, np.asarray(x))[:, used]
    ok = _unpad(data, np.asarray(valid)).astype(bool) & np.all(np.isfinite(x), axis=1)
    # [U, Q, T, E] -> [U, T, Q, E] -> rows [N, Q, S]
    dx = _unpad(data, np.moveaxis(np.asarray(dx), 1, 2))[:, :, used]
    gain = 1.0 + inputs.multiplicative[:, used]
    y = x * gain + inputs.additive[:, used]
    cols = np.zeros(x.shape + (len(tangents),))
    q = 0
    for t, tan in enumerate(tangents):
        if tan.channel in ("parameter", "condition", "state"):
            cols[:, :, t] = dx[:, q] * gain
            q += 1
        else:
            _layer_column(cols, t, tan, data, x)
    ok &= np.all(np.isfinite(cols.reshape(cols.shape[0], -1)), axis=1)
    return Signatures(y, x, ok, cols)


def signatures(
    model: Model,
    data,
    inputs: RowInputs,
    tangents: Sequence[Tangent] = (),
    *,
    like: Signatures | None = None,
    cover: Sequence[Tangent] = (),
) -> Signatures:
    """The extended model at ``inputs`` and its signatures along ``tangents``.

    Args:
        model: the model (float64 enabled by the caller).
        data: the rows (:class:`~jaxcal.diagnosis.data.prepare.LoopData`).
        inputs: :class:`RowInputs`.
        tangents: the directions whose signatures are wanted.
        like: an earlier result at the same ``inputs``: a static model's Jacobians
            are reused (no model evaluation), a model with memory is simulated again.
        cover: more directions whose derivatives a static model's result holds (in
            ``lin``), for later calls ``like`` it; their columns are not formed.

    Returns:
        :class:`Signatures` (``cols [N, S, len(tangents)]``).
    """
    require_x64("the diagnosis needs float64")
    for tan in tangents:
        if tan.channel not in CHANNELS:
            raise ValueError(f"unknown channel {tan.channel!r}; valid: {CHANNELS}")
    if model.is_stateful:
        return _stateful(model, data, inputs, list(tangents))
    if any(t.channel == "state" for t in tangents):
        raise ValueError("a static model has no states")
    lin = None if like is None else like.lin
    return _static(model, data, inputs, list(tangents), lin, cover)
