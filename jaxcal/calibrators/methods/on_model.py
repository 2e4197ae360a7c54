"""The methods on the model (UKF, EKF, least squares): their calibrators, compiled
programs and :class:`~.protocol.Method`.

Each works on the restricted model ``F(w, theta_declared) -> x_used`` (a model with
memory: its transition, the states filtered or fitted with the parameters); the
measurement noise is the explicit input ``noise_std`` (the filter's covariance), the
parameters are scaled by the half-width of the box and start at the nominal values.
The calibrator is pure in the compiled inputs
(:class:`~jaxcal.calibrators.programs.compiled.Inputs`: data, noise, prior, scales;
the states' settings resolved here against each state's natural size,
:func:`state_scale`), its fleet program compiled once per process
(:mod:`jaxcal.calibrators.programs.compiled`), its sample check the model's valid
input box. :func:`on_model_method` builds a method's :class:`~.protocol.Method` from
the two makers of its filter (a static model's and a model with memory's) and its
prior std; the rest is shared.
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator, SampleCheck
from jaxcal.calibrators.methods.options import Built
from jaxcal.calibrators.methods.protocol import Method
from jaxcal.calibrators.programs import compiled
from jaxcal.calibrators.programs.compiled import Inputs
from jaxcal.data.padded import Padded
from jaxcal.problem import Problem


def model_check(problem: Problem) -> SampleCheck | None:
    """The model's valid input box as a sample check (``None``: finiteness only)."""
    if problem.model.condition_range is None:
        return None
    low, high = problem.model.condition_range
    return SampleCheck(w_low=jnp.asarray(low), w_high=jnp.asarray(high))


def model_based_factory(
    problem: Problem, settings, static: Callable, stateful: Callable,
    measure: Callable | None = None,
) -> Callable[[Inputs], Calibrator]:  # fmt: skip
    """``make(inputs) -> Calibrator`` of a method on ``problem``'s model, pure in its
    :class:`Inputs` (call it under ``jax.jit`` with traced inputs): ``static(F,
    settings, measurement, theta0=, theta_scale=, theta_box=)`` on a static model,
    ``stateful(transition, settings, measurement, state_std=, state_q=, theta0=,
    theta_scale=, state_scale=, theta_box=)`` on a model with memory (a method's
    filter makers, e.g. :func:`~jaxcal.calibrators.ukf.make_ukf` and
    :func:`~jaxcal.calibrators.ukf.make_joint_ukf`). ``measure``: ``F(w, theta) ->
    x`` in place of the problem's (a static model only; the paper suite's perturbable
    model)."""
    measurement = compiled.measurement_of
    if measure is not None and problem.model.is_stateful:
        raise ValueError("measure= replaces a static model's F only")
    if not problem.model.is_stateful:
        measure = problem.measure() if measure is None else measure

        def on_static(inputs: Inputs) -> Calibrator:
            return static(
                measure, settings, measurement(inputs), theta0=inputs.theta0,
                theta_scale=inputs.theta_scale,
                theta_box=(inputs.theta_low, inputs.theta_high),  # stays inside
            )  # fmt: skip

        return on_static
    tr = problem.transition()

    def on_stateful(inputs: Inputs) -> Calibrator:
        return stateful(
            tr, settings, measurement(inputs), state_std=inputs.state_std,
            state_q=inputs.state_q, theta0=inputs.theta0,
            theta_scale=inputs.theta_scale, state_scale=inputs.state_scale,
            theta_box=(inputs.theta_low, inputs.theta_high),
        )  # fmt: skip

    return on_stateful


def model_inputs(problem: Problem, cfg, dtype, x_mean=None) -> Inputs:
    """The :class:`Inputs` of a model-based config on ``problem``: the states'
    settings resolved against their natural size (:func:`state_scale`)."""
    if not problem.model.is_stateful:
        return compiled.inputs_of(problem, dtype, x_mean=x_mean)
    states = problem.model.state_names
    scale = state_scale(problem, dtype)
    std = state_option(cfg.state_std, states, 0.01 * scale)
    q = state_option(getattr(cfg, "state_q", None), states, 1e-6 * scale)
    std = np.maximum(std, getattr(cfg, "state_std_floor", 0.0) * scale)
    return compiled.inputs_of(
        problem, dtype, state_std=std, state_q=q, state_scale=scale, x_mean=x_mean
    )


def fleet_built(problem: Problem, cfg, program_of, prior_std, dtype) -> Built:
    """:class:`Built` of a method on the model: its compiled fleet program
    (``program_of() -> program(inputs, w, x, mask) -> CalOutput``) run on the padded
    groups with ``cfg``'s inputs, and the std ``prior_std [P]`` known before a first
    sample."""
    inputs = model_inputs(problem, cfg, dtype)  # first: it checks the settings
    program = program_of()

    def run(padded: Padded, skip=None):
        mask = padded.mask if skip is None else padded.mask & ~np.asarray(skip)
        return program(
            inputs, jnp.asarray(padded.w), jnp.asarray(padded.x), jnp.asarray(mask)
        )

    return Built(run, prior_std)


def stream_calibrator(problem: Problem, cfg, factory) -> Calibrator:
    """One stream's calibrator of a method on the model (``factory`` its
    :attr:`~jaxcal.calibrators.methods.protocol.Method.factory`): the problem's
    noise and prior as constants, in the float dtype JAX defaults to."""
    dtype = jnp.zeros((), float).dtype
    return factory(problem, cfg)(model_inputs(problem, cfg, dtype))


def state_scale(problem: Problem, dtype) -> np.ndarray:
    """``[Z]`` natural size of each hidden state: ``|z0|`` at the nominal parameters
    and the mid-range conditions (1 where that is 0)."""
    tr = problem.transition()
    w_mid = 0.5 * (problem.input_range.w_low + problem.input_range.w_high)
    theta = jnp.asarray(problem.theta_prior, dtype)
    z0 = np.abs(np.asarray(tr.init(jnp.asarray(w_mid, dtype), theta)))
    return np.where(np.isfinite(z0) & (z0 > 0), z0, 1.0).astype(dtype)


def state_option(value, states, default) -> np.ndarray:
    """``state_std`` / ``state_q``: a scalar, ``{state: value}`` or ``[Z]`` (state
    units, >= 0) -> ``[Z]``."""
    if value is None:
        return np.asarray(default)
    if isinstance(value, tuple) and value and isinstance(value[0], tuple):
        value = dict(value)  # a {state: value} frozen by the config
    if isinstance(value, dict):
        unknown = sorted(set(value) - set(states))
        if unknown:
            raise ValueError(
                f"unknown state(s) {unknown}; the model has {list(states)}"
            )
        pairs = zip(states, default, strict=True)
        arr = np.array([float(value.get(n, d)) for n, d in pairs])
    else:
        arr = np.broadcast_to(np.asarray(value, np.float64), (len(states),)).copy()
    if not np.all(np.isfinite(arr) & (arr >= 0)):
        raise ValueError(f"state settings must be finite and >= 0, got {arr.tolist()}")
    return arr.astype(np.asarray(default).dtype)


def on_model_method(
    name: str,
    config: type,
    static: Callable,
    stateful: Callable,
    *,
    label: str,
    prior_std: Callable,
    program: Callable = compiled.fleet_program,
    **traits,
) -> Method:
    """The :class:`~.protocol.Method` of a method on the model.

    Args:
        name, config, label: as :class:`~.protocol.Method`'s; ``config`` holds the
            filter's settings in its ``field_name`` field.
        static, stateful: the filter's makers (``make_ukf``, ``make_joint_ukf``; see
            :func:`model_based_factory`).
        prior_std: ``prior_std(problem, cfg) -> [P]``, what is known of theta before
            a stream's first sample.
        program: ``program(problem, cfg, make, check, dtype) -> run(inputs, w, x,
            mask)``, its compiled fleet program (default
            :func:`~jaxcal.calibrators.programs.compiled.fleet_program`).
        traits: further fields of :class:`~.protocol.Method` (``screening``,
            ``white_std``, ...).
    """
    field = config.field_name

    def factory(problem, cfg, measure=None):
        """``make(inputs) -> Calibrator``: the filter on ``problem``'s model."""
        settings = getattr(cfg, field)
        return model_based_factory(problem, settings, static, stateful, measure)

    def build(problem, cfg, buckets, seed: int = 0):
        del seed

        def program_of():
            make, check = factory(problem, cfg), model_check(problem)
            return program(problem, cfg, make, check, buckets.dtype)

        prior = prior_std(problem, cfg)
        return fleet_built(problem, cfg, program_of, prior, buckets.dtype)

    def make(problem, cfg, buckets=None, seed: int = 0):
        del buckets, seed
        return stream_calibrator(problem, cfg, factory)

    def check(problem, cfg):
        del cfg
        return model_check(problem)

    return Method(
        name=name, config=config, build=build, make=make, check=check,
        factory=factory, label=label, **traits,
    )  # fmt: skip
