"""The method table: every method of :func:`jaxcal.calibrate`, registered once.

Each method is a frozen, hashable config dataclass (:class:`UKF`,
:class:`LeastSquares`, :class:`E2E`, :class:`Policy`) and an entry in
:data:`METHODS`; :func:`config` turns the front door's keyword options into one (a
misspelt option lists the valid ones) and :func:`build` makes it a ready
:class:`Built` for a problem. Adding a method is one config class and one entry.

The model-based methods (UKF, least squares) work on the restricted model
``F(w, theta_declared) -> x_used``; the measurement noise is the explicit input
``noise_std`` (the filter's covariance, :mod:`jaxcal.calibrators.compiled`), the
parameters are scaled by the half-width of the box and start at the nominal values.
Their programs are compiled once per process (:mod:`jaxcal.calibrators.compiled`):
the data, noise, prior and scales are arguments. The E2E network learns the inverse
of the model from simulations over the box at the data's own operating conditions
(:mod:`jaxcal.calibrators.e2e_sim`), or takes given weights; a trained policy is
loaded from its run folder, gated by an absolute policy's run with ``anchor=``.

Every method is run by a jitted fleet runner with a sample check (non-finite
samples and samples outside the valid input box are skipped and flagged). A row
with some outputs missing is used by the UKF and least squares on its observed
outputs and skipped by E2E and a policy (reason ``x_partial``;
:mod:`jaxcal.calibrators.guard`).
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators import compiled
from jaxcal.calibrators.compiled import Inputs
from jaxcal.calibrators.interface import Calibrator, SampleCheck, run_fleet
from jaxcal.calibrators.least_squares import LeastSquaresConfig, make_least_squares
from jaxcal.calibrators.ukf import UKFConfig, make_joint_ukf, make_ukf
from jaxcal.calibrators.window_state import make_window_least_squares
from jaxcal.data.buckets import Buckets
from jaxcal.data.dataset import Padded
from jaxcal.problem import Problem


def _frozen(value):
    """A state option as a hashable value (a ``{state: value}`` as sorted pairs, an
    array as a tuple); what cannot be read is left for :func:`_state_option` to
    refuse with its message."""
    try:
        if isinstance(value, dict):
            return tuple(sorted((k, float(v)) for k, v in value.items()))
        if value is None or isinstance(value, (int, float, str)):
            return value
        return tuple(np.ravel(np.asarray(value, np.float64)).tolist())
    except (TypeError, ValueError):
        return value


@dataclasses.dataclass(frozen=True)
class UKF:
    """The unscented Kalman filter on the model (random-walk parameters); with hidden
    states the joint state-and-parameter filter. ``filter``: its settings (``r`` is
    1: the noise is the ``noise_std`` input); ``state_std`` / ``state_q``: the
    initial state's std and the states' process noise (scalar, per state, or
    ``{state: value}``; default 1 % / 1e-6 of each state's size)."""

    filter: UKFConfig = UKFConfig(r=1.0)
    state_std: Any = None
    state_q: Any = None

    name = "ukf"
    field_type = UKFConfig
    field_name = "filter"


@dataclasses.dataclass(frozen=True)
class LeastSquares:
    """Sliding-window least squares on the model (Levenberg-Marquardt); with hidden
    states the moving-window fit of the parameters and the window's initial state.
    ``solver``: its settings (``r`` is 1); ``state_std``: the window start's std."""

    solver: LeastSquaresConfig = LeastSquaresConfig(r=1.0)
    state_std: Any = None

    name = "ls"
    field_type = LeastSquaresConfig
    field_name = "solver"


@dataclasses.dataclass(frozen=True)
class E2E:
    """The E2E network ``theta_t = G(w_t, x_t, x_{t-1})``: given weights
    (``e2e=``), else trained on simulations of the model (E2E-sim) with
    ``e2e_config``; ``e2e_window``: past samples G reads (a model with memory:
    16); ``e2e_copies``: simulated fleets."""

    e2e: Any = dataclasses.field(default=None, compare=False)
    e2e_config: Any = None
    e2e_window: int | None = None
    e2e_copies: int = 8

    name = "e2e"


@dataclasses.dataclass(frozen=True)
class Policy:
    """A trained tracking policy, ``run=<run folder>``; an incremental (feedback)
    policy's run with ``anchor=<absolute policy's run folder>`` is gated by it where
    the model misfits the data (:mod:`jaxcal.calibrators.gated`)."""

    run: Any = dataclasses.field(default=None, compare=False)
    anchor: Any = dataclasses.field(default=None, compare=False)

    name = "policy"


class Built(NamedTuple):
    """A method ready to run: ``run(padded, skip=None) -> CalOutput`` per padded
    group (``skip [U, T]``: cells skipped like padding), and ``prior_std [P]``,
    what is known of theta before a stream's first sample."""

    run: Callable
    prior_std: np.ndarray
    calibrator: Calibrator | None = None  # E2E, a policy (the model-based: make())


def options_of(config_type) -> tuple[str, ...]:
    """The keyword options of a method's config."""
    names = [f.name for f in dataclasses.fields(config_type)]
    inner = getattr(config_type, "field_type", None)
    if inner is not None:
        names.remove(config_type.field_name)
        names += [f.name for f in dataclasses.fields(inner) if f.name != "r"]
    return tuple(names)


def config(method: str, options: dict):
    """The config of ``method`` from keyword ``options`` (every one consumed).

    Raises:
        ValueError: an unknown method, or an option the method does not take
            (listing the valid ones and the closest match).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {tuple(METHODS)}, got {method!r}")
    config_type = METHODS[method]
    valid = options_of(config_type)
    unknown = sorted(set(options) - set(valid))
    if unknown:
        hints = [difflib.get_close_matches(k, valid, n=1) for k in unknown]
        said = "; ".join(
            f"{k!r}" + (f" (did you mean {h[0]!r}?)" if h else "")
            for k, h in zip(unknown, hints, strict=True)
        )
        raise ValueError(
            f"unknown option(s) for method={method!r}: {said}; its options are "
            f"{sorted(valid)}"
        )
    kwargs = {}
    inner = getattr(config_type, "field_type", None)
    if inner is not None:
        names = {f.name for f in dataclasses.fields(inner)} - {"r"}
        inner_kw = {k: options[k] for k in options if k in names}
        kwargs[config_type.field_name] = inner(r=1.0, **inner_kw)
    for f in dataclasses.fields(config_type):
        if f.name in options:
            value = options[f.name]
            kwargs[f.name] = _frozen(value) if f.name.startswith("state_") else value
    return config_type(**kwargs)


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
    norm = compiled.norm_of
    if measure is not None and problem.model.is_stateful:
        raise ValueError("measure= replaces a static model's F only")
    if not problem.model.is_stateful:
        measure = problem.measure() if measure is None else measure
        make = make_ukf if ukf else make_least_squares

        def static(inputs: Inputs) -> Calibrator:
            return make(
                measure, settings, norm(inputs), theta0=inputs.theta0,
                theta_scale=inputs.theta_scale,
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
                tr, settings, norm(inputs), state_std=inputs.state_std,
                state_q=inputs.state_q, **common,
            )  # fmt: skip
        return make_window_least_squares(
            tr, settings, norm(inputs), state_std=inputs.state_std, **common
        )

    return stateful


def model_inputs(problem: Problem, cfg, dtype, x_mean=None) -> Inputs:
    """The :class:`Inputs` of a model-based config on ``problem``: the states'
    settings resolved against their natural size (:func:`state_scale`)."""
    if not problem.model.is_stateful:
        return compiled.inputs_of(problem, dtype, x_mean=x_mean)
    states = problem.model.state_names
    scale = state_scale(problem, dtype)
    std = _state_option(cfg.state_std, states, 0.01 * scale)
    q = _state_option(getattr(cfg, "state_q", None), states, 1e-6 * scale)
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


def _model_based(problem: Problem, cfg, dtype) -> Built:
    inputs = model_inputs(problem, cfg, dtype)  # first: it checks the settings
    if isinstance(cfg, UKF):
        filt = ukf_program(problem, cfg, dtype)
        program = lambda *args: filt(*args)[0]  # noqa: E731
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


_FLEET = jax.jit(run_fleet, static_argnums=0)  # one dispatch cache per process


def make_runner(check: SampleCheck | None):
    """``run(calibrator, padded, skip=None) -> CalOutput``: the fleet scan of a
    calibrator built outside the compiled programs (E2E, a policy), jitted; the same
    calibrator object again runs without tracing again."""
    fleet = _FLEET

    def run(calibrator: Calibrator, padded: Padded, skip=None):
        mask = padded.mask if skip is None else padded.mask & ~np.asarray(skip)
        return fleet(
            calibrator, jnp.asarray(padded.w), jnp.asarray(padded.x),
            jnp.asarray(mask), check=check,
        )  # fmt: skip

    return run


def _learned(problem: Problem, cal: Calibrator, check) -> Built:
    runner = make_runner(check)
    uniform = problem.theta_half_width / np.sqrt(3.0)
    return Built(lambda padded, skip=None: runner(cal, padded, skip), uniform, cal)


def build(problem: Problem, cfg, buckets: Buckets, seed: int = 0) -> Built:
    """:class:`Built` of the config ``cfg`` (:func:`config`) on ``problem``; ``buckets``
    are the data (E2E-sim trains on their conditions and float dtype)."""
    if isinstance(cfg, (UKF, LeastSquares)):
        return _model_based(problem, cfg, buckets.dtype)
    if isinstance(cfg, E2E):
        from jaxcal.calibrators.policy import range_check  # E2E's own imports

        cal = _e2e(problem, buckets, seed, cfg)
        return _learned(problem, cal, range_check(problem))
    cal, check = _policy(problem, cfg)
    return _learned(problem, cal, check)


def make(problem: Problem, cfg, buckets: Buckets | None = None, seed: int = 0):
    """The method as one ``Calibrator(init, step)`` on ``problem`` (a stream's
    calibrator: the model-based ones with the problem's noise and prior as
    constants, in the float dtype JAX defaults to)."""
    if isinstance(cfg, (UKF, LeastSquares)):
        dtype = jnp.zeros((), float).dtype
        return model_based_factory(problem, cfg)(model_inputs(problem, cfg, dtype))
    if buckets is None and isinstance(cfg, E2E) and cfg.e2e is None:
        raise ValueError("E2E-sim trains on the data's conditions: pass buckets=")
    return build(problem, cfg, buckets, seed).calibrator


METHODS: dict[str, type] = {c.name: c for c in (UKF, LeastSquares, E2E, Policy)}


def state_scale(problem: Problem, dtype) -> np.ndarray:
    """``[Z]`` natural size of each hidden state: ``|z0|`` at the nominal parameters
    and the mid-range conditions (1 where that is 0)."""
    tr = problem.transition()
    w_mid = 0.5 * (problem.input_range.w_low + problem.input_range.w_high)
    theta = jnp.asarray(problem.theta_prior, dtype)
    z0 = np.abs(np.asarray(tr.init(jnp.asarray(w_mid, dtype), theta)))
    return np.where(np.isfinite(z0) & (z0 > 0), z0, 1.0).astype(dtype)


def _state_option(value, states, default) -> np.ndarray:
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


def _e2e(problem: Problem, buckets: Buckets, seed: int, cfg: E2E) -> Calibrator:
    """A given E2E network, or one trained on simulations of the model (E2E-sim)."""
    from jaxcal.calibrators.e2e import E2EConfig, make_e2e_calibrator
    from jaxcal.calibrators.e2e_sim import fit_e2e_sim
    from jaxcal.nets.mlp import RegressorConfig

    params = cfg.e2e
    measure = problem.measure() if not problem.model.is_stateful else None
    window = cfg.e2e_window
    window = int((16 if measure is None else 0) if window is None else window)
    if params is None:
        fit = cfg.e2e_config or E2EConfig(
            hidden_sizes=(64, 64),
            fit=RegressorConfig(
                learning_rate=1e-3, batch_size=256, num_epochs=60,
                validation_fraction=0.1, patience=10,
            ),
        )  # fmt: skip
        copies = int(cfg.e2e_copies)
        params = fit_e2e_sim(problem, buckets, fit, seed, copies, window)[0]
    if measure is not None:
        return make_e2e_calibrator(params, measure)
    return make_e2e_calibrator(
        params, transition=problem.transition(),
        theta0=jnp.asarray(problem.theta_prior, buckets.dtype),
    )  # fmt: skip


def _policy(problem: Problem, cfg: Policy) -> tuple[Calibrator, SampleCheck | None]:
    """A trained policy from ``run=<folder>`` and its sample check (the run's own
    training range, not the range of the data being calibrated); its names must
    match the problem, and the problem's model must be the run's own (by names and
    by outputs at probe points, :mod:`jaxcal.training.model_check`). With
    ``anchor=<folder>`` (an absolute policy's run with its
    band) the run, an incremental policy, is gated by it (:mod:`jaxcal.calibrators.
    gated`): the feedback while the model fits the data, the anchor where not."""
    # The run loader belongs to the training layer: a trained policy is one of its
    # artefacts (imported here, when the method is asked for, not at import time).
    from jaxcal.training.runs import (
        LoadedRun,
        check_run_model,
        load_calibrator,
        load_run,
        run_check,
    )

    run_dir, anchor_dir = cfg.run, cfg.anchor
    if not run_dir:
        raise ValueError("method='policy' needs run=<trained run folder>")
    run = run_dir if isinstance(run_dir, LoadedRun) else load_run(run_dir)
    _check_run(problem, run)
    check_run_model(run, problem.model)  # the policy runs with the run's own model
    anchor = None
    if anchor_dir:  # the feedback gated by an absolute policy (calibrators.gated)
        anchor = load_run(anchor_dir)
        _check_run(problem, anchor)
        check_run_model(anchor, problem.model)
    # one calibrator per (run, checkpoint, anchor) in a process: a repeat call
    # reuses its compiled program (the policy's weights are the program's constants)
    key = (
        str(run.run_dir), run.step,
        None if anchor is None else (str(anchor.run_dir), anchor.step),
    )  # fmt: skip
    cal = compiled.cached_value(("policy", key), lambda: load_calibrator(run, anchor))
    return cal, run_check(run)


def _check_run(problem: Problem, run) -> None:
    """A loaded run's names must match the problem's (else a ValueError)."""
    run_dir = run.run_dir
    names = run.problem.theta_names
    if tuple(names) != problem.theta_names:
        raise ValueError(
            f"run {run_dir} calibrates {list(names)}, not "
            f"{list(problem.theta_names)}: pass theta={list(names)}"
        )
    if run.problem.model.condition_names != problem.model.condition_names:
        raise ValueError(
            f"run {run_dir} was trained on model {run.problem.model.name!r} with "
            f"conditions {list(run.problem.model.condition_names)}, not "
            f"{list(problem.model.condition_names)}"
        )
    outputs = run.problem.output_names
    if tuple(outputs) != problem.output_names:
        raise ValueError(
            f"run {run_dir} uses outputs {list(outputs)}, the data give "
            f"{list(problem.output_names)}: pass outputs={list(outputs)}"
        )
