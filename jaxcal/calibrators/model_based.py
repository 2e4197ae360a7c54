"""The model-based methods (UKF, least squares) on a problem: their calibrators and
compiled programs.

Both work on the restricted model ``F(w, theta_declared) -> x_used`` (a model with
memory: its transition, the states filtered or fitted with the parameters); the
measurement noise is the explicit input ``noise_std`` (the filter's covariance,
:mod:`jaxcal.calibrators.compiled`), the parameters are scaled by the half-width of
the box and start at the nominal values. Their programs are compiled once per
process (:mod:`jaxcal.calibrators.compiled`): the data, noise, prior and scales are
arguments (:class:`~jaxcal.calibrators.compiled.Inputs`), the states' settings
resolved here against each state's natural size (:func:`state_scale`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators import compiled
from jaxcal.calibrators.compiled import Inputs
from jaxcal.calibrators.interface import Calibrator, SampleCheck
from jaxcal.calibrators.least_squares import make_least_squares
from jaxcal.calibrators.method_configs import UKF, Built, LeastSquares
from jaxcal.calibrators.ukf import make_joint_ukf, make_ukf
from jaxcal.calibrators.window_state import make_window_least_squares
from jaxcal.data.padded import Padded
from jaxcal.problem import Problem


def model_check(problem: Problem) -> SampleCheck | None:
    """The model's valid input box as a sample check (``None``: finiteness only)."""
    if problem.model.condition_range is None:
        return None
    low, high = problem.model.condition_range
    return SampleCheck(w_low=jnp.asarray(low), w_high=jnp.asarray(high))


def model_based_factory(
    problem: Problem, cfg, measure: Callable | None = None
) -> Callable[[Inputs], Calibrator]:
    """``make(inputs) -> Calibrator`` of a :class:`UKF` or :class:`LeastSquares`
    config on ``problem``'s model: pure in its :class:`Inputs` (call it under
    ``jax.jit`` with traced inputs). ``measure``: ``F(w, theta) -> x`` in place of
    the problem's (a static model only; the paper suite's perturbable model)."""
    ukf = isinstance(cfg, UKF)
    settings = cfg.filter if ukf else cfg.solver
    measurement = compiled.measurement_of
    if measure is not None and problem.model.is_stateful:
        raise ValueError("measure= replaces a static model's F only")
    if not problem.model.is_stateful:
        measure = problem.measure() if measure is None else measure
        make = make_ukf if ukf else make_least_squares

        def static(inputs: Inputs) -> Calibrator:
            return make(
                measure, settings, measurement(inputs), theta0=inputs.theta0,
                theta_scale=inputs.theta_scale,
                theta_box=(inputs.theta_low, inputs.theta_high),  # stays inside
            )  # fmt: skip

        return static
    tr = problem.transition()
    if not ukf and settings.prior_std is None:  # a window without excitation
        settings = dataclasses.replace(settings, prior_std=1.0)  # must not run off

    def stateful(inputs: Inputs) -> Calibrator:
        common = dict(
            theta0=inputs.theta0, theta_scale=inputs.theta_scale,
            state_scale=inputs.state_scale,
            theta_box=(inputs.theta_low, inputs.theta_high),
        )  # fmt: skip
        if ukf:
            return make_joint_ukf(
                tr, settings, measurement(inputs), state_std=inputs.state_std,
                state_q=inputs.state_q, **common,
            )  # fmt: skip
        return make_window_least_squares(
            tr, settings, measurement(inputs), state_std=inputs.state_std, **common
        )

    return stateful


def model_inputs(problem: Problem, cfg, dtype, x_mean=None) -> Inputs:
    """The :class:`Inputs` of a model-based config on ``problem``: the states'
    settings resolved against their natural size (:func:`state_scale`)."""
    if not problem.model.is_stateful:
        return compiled.inputs_of(problem, dtype, x_mean=x_mean)
    states = problem.model.state_names
    scale = state_scale(problem, dtype)
    std = state_option(cfg.state_std, states, 0.01 * scale)
    q = state_option(getattr(cfg, "state_q", None), states, 1e-6 * scale)
    if isinstance(cfg, LeastSquares):
        std = np.maximum(std, 1e-9 * scale)
    return compiled.inputs_of(
        problem, dtype, state_std=std, state_q=q, state_scale=scale, x_mean=x_mean
    )


def ukf_program(problem: Problem, cfg: UKF, dtype):
    """The UKF's compiled program with innovations (:func:`compiled.filter_program`):
    the screening passes and the method's own run share it."""
    make = model_based_factory(problem, cfg)
    return compiled.filter_program(problem, cfg, make, model_check(problem), dtype)


def build_model_based(problem: Problem, cfg, dtype) -> Built:
    """:class:`Built` of a :class:`UKF` or :class:`LeastSquares` config on ``problem``:
    its compiled fleet program over the padded groups, and the prior std (the UKF's
    ``prior_std`` of the half-width, least squares a uniform's over the box)."""
    inputs = model_inputs(problem, cfg, dtype)  # first: it checks the settings
    if isinstance(cfg, UKF):
        filt = ukf_program(problem, cfg, dtype)

        def program(inputs, w, x, mask):  # nothing to probe: the screen's program
            return filt(inputs, w, x, mask, jnp.zeros_like(mask))[0]

    else:
        make, check = model_based_factory(problem, cfg), model_check(problem)
        program = compiled.fleet_program(problem, cfg, make, check, dtype)

    def run(padded: Padded, skip=None):
        mask = padded.mask if skip is None else padded.mask & ~np.asarray(skip)
        return program(
            inputs, jnp.asarray(padded.w), jnp.asarray(padded.x), jnp.asarray(mask)
        )

    half = problem.theta_half_width
    prior = cfg.filter.prior_std * half if isinstance(cfg, UKF) else half / np.sqrt(3)
    return Built(run, prior)


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
