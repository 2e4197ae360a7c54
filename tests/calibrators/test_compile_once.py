"""``jaxcal.calibrate`` compiles once per process (issue 26): a repeat call on data
of the same shape — other values, another noise — neither traces nor compiles."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from jax import monitoring

import jaxcal
from jaxcal.calibrators.programs import compiled, traced_key

TRACE = "/jax/core/compile/jaxpr_trace_duration"
COMPILE = "/jax/core/compile/backend_compile_duration"
_events = []
monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: _events.append(name)
)


def _tank(w, theta):
    level = w[1] / theta[0]
    return jnp.stack([level, 20 + w[0] / (w[1] * (1 + theta[1])), theta[0] * level])


def _lag(z, w, theta):
    a = jnp.exp(-1.0 / theta[0])
    z = a * z + (1 - a) * w[0]
    return z, jnp.stack([theta[1] * z[0] + 0.2 * w[0], w[0] - 0.5 * z[0] ** 2])


STATIC = jaxcal.Model.from_function(
    _tank, conditions=("heat", "inflow"),
    parameters={"leak": (1.0, 0.5, 2.0), "loss": (0.1, 0.0, 0.5)},
    outputs=("level", "temp", "outflow"),
)  # fmt: skip
MEMORY = jaxcal.Model.from_step(
    _lag, init_state=lambda w0, theta: w0[:1], states=("z",), conditions=("u",),
    parameters={"tau": (5.0, 2.0, 10.0), "gain": (1.0, 0.5, 2.0)},
    outputs=("y1", "y2"),
)  # fmt: skip


def _data(model, seed):
    rng = np.random.default_rng(seed)
    if model is STATIC:
        w = rng.uniform([5.0, 0.5], [30.0, 2.0], (80, 2))
        x = np.asarray(jax.vmap(_tank)(w, np.tile([1.2, 0.2], (80, 1))))
    else:
        w = np.repeat(rng.uniform(0.2, 1.0, 8), 10)[:, None]
        step = lambda z, w_t: _lag(z, w_t, jnp.array([3.0, 1.4]))  # noqa: E731
        x = np.asarray(jax.lax.scan(step, jnp.asarray(w[0]), jnp.asarray(w))[1])
    x = x + 0.01 * rng.standard_normal(x.shape)
    cols = model.condition_names + model.output_names
    frame = pd.DataFrame(np.hstack([w, x]), columns=cols)
    frame.insert(0, "unit", np.repeat([1, 2], len(frame) // 2))
    return frame


def _events_of(call):
    _events.clear()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = call()
    return result, _events.count(TRACE), _events.count(COMPILE)


# each axis both ways (model, method, noise estimated or given) in four calls
CASES = [
    (STATIC, "ukf", None), (STATIC, "ls", 0.02), (MEMORY, "ukf", 0.02),
    (MEMORY, "ls", None),
]  # fmt: skip


@pytest.mark.parametrize(
    "model, method, noise", CASES,
    ids=["static-ukf-estimated", "static-ls-given", "memory-ukf-given",
         "memory-ls-estimated"],
)  # fmt: skip
def test_a_repeat_call_neither_traces_nor_compiles(model, method, noise):
    given = None if noise is None else dict.fromkeys(model.output_names, noise)

    def call(seed):
        data = _data(model, seed)  # made outside the counted call
        return lambda: jaxcal.calibrate(model, data, method, noise=given)

    compiled.clear()  # the first call builds (earlier tests may have)
    first, traces, _ = _events_of(call(0))
    assert traces > 0  # the listener sees this process's traces
    built = dict(compiled._COUNTS)
    # a call traces the user's model alone (milliseconds), to see whether a global
    # it reads has changed (issue 42): those traces, never the calibrator's
    dtype = jnp.zeros(()).dtype
    _, model_traces, _ = _events_of(lambda: traced_key.refresh(model, dtype))
    assert 0 < model_traces <= 4  # the step and its derivative, init and its
    # other values of the same shape: the data and the noise are arguments
    again, traces, compiles = _events_of(call(1))
    assert (traces, compiles) == (model_traces, 0)
    assert dict(compiled._COUNTS) == built
    assert not np.allclose(first.theta, again.theta)
    # the same values give the same numbers as the first call
    same, traces, compiles = _events_of(call(0))
    assert (traces, compiles) == (model_traces, 0)
    np.testing.assert_array_equal(same.theta, first.theta)


def test_other_settings_build_their_own_program():
    data, noise = _data(STATIC, 0), dict.fromkeys(STATIC.output_names, 0.02)
    jaxcal.calibrate(STATIC, data, "ukf", noise=noise)
    built = dict(compiled._COUNTS)
    jaxcal.calibrate(STATIC, data, "ukf", noise=noise, q=0.02)
    assert dict(compiled._COUNTS)["filter"] == built["filter"] + 1


def test_a_misspelt_option_lists_the_valid_ones():
    with pytest.raises(ValueError, match=r"'qq' \(did you mean 'q'\?\).*'prior_std'"):
        jaxcal.calibrate(STATIC, _data(STATIC, 0), "ukf", qq=0.1)
    with pytest.raises(ValueError, match="'state_q'.*options are.*'window'"):
        jaxcal.calibrate(MEMORY, _data(MEMORY, 0), "ls", state_q=0.1)


def test_the_source_digest_covers_the_whole_package():
    """A program kept on disk is keyed by every file of jaxcal, the model's physics
    included, not only by the calibrators' own folder (the one its module sits in)."""
    from pathlib import Path

    from jaxcal.calibrators.programs import on_disk

    assert on_disk.PACKAGE_ROOT == Path(jaxcal.__file__).resolve().parent
