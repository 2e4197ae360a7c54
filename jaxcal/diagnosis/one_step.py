"""The diagnosis of a model with memory: residuals of the one-step prediction.

The diagnosis (:mod:`jaxcal.diagnosis.pipeline`) fits, screens and extends a static
model ``x = F(w, theta)``. A model with hidden states,
``(z_t, x_t) = step(z_{t-1}, w_t, theta)``, becomes one by conditioning on the
state: the joint state-and-parameter UKF (:func:`jaxcal.calibrate`, declared
parameters only) estimates ``z_{t-1}`` from the data up to ``t - 1``, and

    x_t = F1(w_t, z_{t-1}; theta) = step(z_{t-1}, w_t, theta)[1]

is the one-step prediction. Its residual is the innovation of the filter (the
standard residual of a state-space model; Harvey 1989, sec. 5.4): an effect the
model lacks shows in it as it does in a static model's residual, and the candidate
effects are formed as for a static model (parameters, sensor biases and drifts,
offsets of the *logged* conditions; the estimated states are inputs, never offset).

Known weakness (measured in ``tests/diagnosis/test_diagnose_stateful.py``): an
effect on an output that pins a state (a bias on a sensor that reads the state
almost directly) is partly absorbed by the filtered state, and shows up as an
effect on the other outputs. A slow parameter random walk (:data:`PARAMETER_Q`)
limits it; an output-error diagnosis that re-simulates the state with every
candidate is the remedy and is not built yet.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.model import Model, Variable

PREV = "_prev"  # suffix of the estimated-state conditions
PARAMETER_Q = 1e-3  # random-walk std per sample of the filter (half-widths)
SETTLE = 0.1  # share of each unit's first rows left out while the filter settles


def one_step_model(model: Model) -> Model:
    """The static model ``F1([w, z_prev], theta) = step(z_prev, w, theta)[1]``."""
    num_w = len(model.conditions)
    hints = model.diagnosis
    if hints.offset_conditions is None:  # generic offsets: the logged conditions only
        hints = hints._replace(offset_conditions=model.condition_names)

    def fn(w_aug, theta):
        _, x, info = model.step(w_aug[num_w:], w_aug[:num_w], theta)
        return x, info

    low = high = None
    if model.condition_range is not None:
        num_z = len(model.states)
        low = np.concatenate([model.condition_range[0], np.full(num_z, -np.inf)])
        high = np.concatenate([model.condition_range[1], np.full(num_z, np.inf)])
    return Model.from_function(
        fn,
        conditions=(
            *model.conditions,
            *(Variable(s.name + PREV, s.unit) for s in model.states),
        ),
        parameters={p.name: p for p in model.parameters},
        outputs=model.outputs,
        name=f"{model.name} (one step)",
        condition_range=None if low is None else (low, high),
        input_check=(
            None
            if model.input_check is None
            else (lambda w_aug: model.input_check(w_aug[:num_w]))
        ),
        x64=model.x64,
        diagnosis=hints,
    )


def one_step_data(
    model: Model,
    data: Dataset,
    declared: Sequence[str],
    noise_std: Mapping[str, float] | None = None,
    outputs: Sequence[str] | None = None,
) -> tuple[Dataset, str]:
    """``data`` with the filtered previous state as extra conditions.

    Returns:
        ``(dataset, note)``: the rows the filter skipped and each unit's first
        :data:`SETTLE` share of rows are dropped (the note says how many).
    """
    from jaxcal.calibrators.front import calibrate

    # A slow parameter random walk: with the default one, theta moves with every
    # change of the conditions and the state absorbs what the model lacks.
    result = calibrate(
        model, data, "ukf", theta=tuple(declared), noise=noise_std, outputs=outputs,
        q=PARAMETER_Q,
    )  # fmt: skip
    data = data.for_model(model, outputs)
    states = result.states
    prev = np.empty_like(states)
    first = np.r_[True, data.unit[1:] != data.unit[:-1]]
    prev[1:] = states[:-1]
    full = np.tile(model.nominal, (len(states), 1))
    full[:, model.parameter_index(declared)] = result.theta
    # each unit's first row: its initial state at the filter's first estimate
    init = jax.jit(jax.vmap(model.init_state))
    prev[first] = np.asarray(
        init(jnp.asarray(data.w[first]), jnp.asarray(full[first], data.w.dtype))
    )
    # While the filter settles its state is not yet known; a residual there is the
    # filter's start-up, not an effect: each unit's first share of rows is left out.
    index = np.arange(len(first)) - np.maximum.accumulate(
        np.where(first, np.arange(len(first)), 0)
    )
    length = np.bincount(np.cumsum(first) - 1)[np.cumsum(first) - 1]
    settled = index >= np.ceil(SETTLE * length)
    keep = result.valid & np.all(np.isfinite(prev), axis=1) & settled
    names = (*data.condition_names, *(s + PREV for s in model.state_names))
    aug = dataclasses.replace(
        data,
        w=np.concatenate([data.w, prev], axis=1)[keep],
        x=data.x[keep],
        condition_names=names,
        unit=data.unit[keep],
        time=data.time[keep],
        theta=None if data.theta is None else data.theta[keep],
        split=None if data.split is None else data.split[keep],
        row=None if data.row is None else data.row[keep],
    )
    note = (
        f"one-step residuals of {model.name!r}: states {list(model.state_names)} "
        f"filtered by the joint UKF on {list(declared)}; "
        f"{int((~keep).sum())} rows dropped (each unit's first "
        f"{SETTLE:.0%} while the filter settles, and rows it skipped)"
    )
    return aug, note
