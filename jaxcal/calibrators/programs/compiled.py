"""Model-based calibrators compiled once per process.

A closure capturing a call's numbers (noise, outputs' centre, prior) as constants
would make every call compile again, which on a model with an iterative solver
costs far more than its compute. So a program is built once per
(model, calibrated parameters, outputs, their base values, method settings, float
dtype, kind) and kept; everything that changes from call to call is an argument
(:class:`Inputs`). A repeat call with data of the same padded shape reuses the
compiled program, and because the program holds no call's numbers, JAX's
persistent compilation cache (:mod:`jaxcal.cache`) finds it in a new process.

The measurement noise is an explicit input, the filter's measurement covariance
``R = diag(noise_std^2)``: :func:`measurement_of` makes the calibrators'
:class:`~jaxcal.calibrators.interface.Measurement` of it (the outputs centred on
``x_mean`` and expressed in units of ``noise_std``, where ``R`` is the identity;
:mod:`jaxcal.calibrators.ukf`).
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Hashable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator, Measurement, run_fleet
from jaxcal.calibrators.programs.on_disk import kept, serialisable
from jaxcal.calibrators.programs.traced_key import fingerprint, traced_key
from jaxcal.problem import Problem
from jaxcal.typedefs import Array

MAX_PROGRAMS = 64  # programs kept per process (least recently used dropped)


@serialisable
class Inputs(NamedTuple):
    """The numbers of one calibration, arguments of its compiled program."""

    x_mean: Array  # [S] the outputs' centre
    noise_std: Array  # [S] measurement noise std: R = diag(noise_std^2)
    theta0: Array  # [P] prior mean / first estimate
    theta_scale: Array  # [P] the parameters' natural scale (half the box)
    theta_low: Array  # [P] the box
    theta_high: Array  # [P]
    state_std: Array  # [Z] initial-state std (empty for a static model)
    state_q: Array  # [Z] process noise on the states per step
    state_scale: Array  # [Z] natural size of each state


def inputs_of(
    problem: Problem, dtype, *, state_std=None, state_q=None, state_scale=None,
    x_mean=None,
) -> Inputs:  # fmt: skip
    """:class:`Inputs` of ``problem`` in ``dtype`` (``state_*``: resolved ``[Z]``
    arrays, empty for a static model; ``x_mean`` default the problem's)."""
    empty = np.zeros((len(problem.model.state_names),))

    def arr(v):
        return jnp.asarray(np.asarray(empty if v is None else v, np.float64), dtype)

    return Inputs(
        x_mean=arr(problem.norm.x_mean if x_mean is None else x_mean),
        noise_std=arr(problem.noise_std),
        theta0=arr(problem.theta_prior),
        theta_scale=arr(problem.theta_half_width),
        theta_low=arr(problem.theta_low),
        theta_high=arr(problem.theta_high),
        state_std=arr(state_std),
        state_q=arr(state_q),
        state_scale=arr(state_scale),
    )


_PROGRAMS: collections.OrderedDict = collections.OrderedDict()
_COUNTS = collections.Counter()  # builds per kind (tests read it)


def problem_key(problem: Problem, dtype) -> tuple:
    """What a program depends on in ``problem`` beyond its :class:`Inputs`: the model
    (by identity, and for a user's model what its functions computed when last
    traced: a global they read may have changed, :func:`~jaxcal.calibrators.
    traced_key.refresh`), the names and the undeclared parameters' values."""
    model = problem.model
    return (
        id(model),
        model.origin or fingerprint(model, dtype),
        problem.theta_names,
        problem.output_names,
        np.asarray(problem.theta_base, np.float64).tobytes(),
        np.dtype(dtype).name,
    )


def _remember(key: Hashable, kind: str, keep, build: Callable):
    """``build()`` once per ``key`` (least recently used dropped past
    :data:`MAX_PROGRAMS`); ``keep`` is held with it (a model whose id is in ``key``
    must not be freed and its id reused)."""
    if key not in _PROGRAMS:
        _PROGRAMS[key] = (keep, build())
        _COUNTS[kind] += 1
    _PROGRAMS.move_to_end(key)
    while len(_PROGRAMS) > MAX_PROGRAMS:
        _PROGRAMS.popitem(last=False)
    return _PROGRAMS[key][1]


def cached(kind: str, problem: Problem, settings: Hashable, dtype, build: Callable):
    """The program ``build()`` made once for (``kind``, ``problem``'s key,
    ``settings``, ``dtype``) in this process; ``build`` returns a jitted function.
    It is also kept on disk for the next process
    (:func:`~jaxcal.calibrators.programs.on_disk.kept`), under the built-in model's name
    or a user model's traced digest (:mod:`~jaxcal.calibrators.programs.traced_key`)."""
    key = (kind, problem_key(problem, dtype), settings)

    def build_kept():
        origin = problem.model.origin or traced_key(problem.model, dtype)
        # the disk key: the model named by origin or digest instead of id/fingerprint
        disk = None if origin is None else (kind, origin, *key[1][2:], settings)
        return kept(build(), disk)

    return _remember(key, kind, problem.model, build_kept)


def cached_value(key: tuple, build: Callable):
    """``build()`` made once per ``key`` in this process (kept like a program; its
    first entry names its kind in the build counts)."""
    return _remember(("value", key), key[0], None, build)


def clear() -> None:
    """Forget every program (the next call builds and compiles again)."""
    _PROGRAMS.clear()


def fleet_program(
    problem: Problem, settings: Hashable, make: Callable[[Inputs], Calibrator], check,
    dtype,
):  # fmt: skip
    """``run(inputs, w [U,T,W], x [U,T,S], mask [U,T]) -> CalOutput``: the fleet
    scan of the calibrator ``make(inputs)`` with the sample ``check``, jitted once
    per (problem key, ``settings``)."""

    def build():
        def run(inputs: Inputs, w, x, mask):
            return run_fleet(_traced_once(make(inputs)), w, x, mask, check=check)

        return jax.jit(run)

    return cached("fleet", problem, settings, dtype, build)


def filter_program(
    problem: Problem, settings: Hashable, make: Callable[[Inputs], Calibrator], check,
    dtype,
):  # fmt: skip
    """``run(inputs, w, x, mask, probe) -> (CalOutput, innovation [U,T,S], its
    std)``: the fleet scan of a filter ``make(inputs)`` whose ``aux`` holds
    ``innovation`` and ``innovation_std``, each row's taken from the state before it:
    at the rows used, and at the ``probe [U, T]`` rows (skipped, yet judged: how the
    row looks to the filter that did not use it; NaN at other rows). The probe rides
    on the scan's own step (:func:`~jaxcal.calibrators.guard.probed_update`), so the
    innovations cost no model evaluation beyond the filter's. One program serves the
    screening passes and the UKF's own run (:mod:`jaxcal.calibrators.front.screen`)."""

    def build():
        def run(inputs: Inputs, w, x, mask, probe):
            cal = _traced_once(make(inputs))
            out = run_fleet(cal, w, x, mask, check=check, probe=probe)
            fresh = out.aux["fresh"]
            aux = {k: v for k, v in out.aux.items() if k != "fresh"}
            innovation, std = fresh["innovation"], fresh["innovation_std"]
            return out._replace(aux=aux), innovation, std

        return jax.jit(run)

    return cached("filter", problem, settings, dtype, build)


def _traced_once(cal: Calibrator) -> Calibrator:
    """``cal`` with its step as a nested ``jax.jit``: the runner traces a step twice
    (its output shapes, the scan body) and a nested jit keeps the first trace's jaxpr
    for the other (what a new process pays on a warm cache)."""
    return cal._replace(step=jax.jit(cal.step))


def measurement_of(inputs: Inputs) -> Measurement:
    """The calibration's measurement model: the outputs centred on ``x_mean`` and in
    units of their noise std (with the configs' ``r = 1``, ``R = diag(noise_std^2)``
    and the identity in those units)."""
    return Measurement(centre=inputs.x_mean, noise_std=inputs.noise_std)
