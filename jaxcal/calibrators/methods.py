"""The method table: every method of :func:`jaxcal.calibrate`, registered once.

Each method is a frozen, hashable config dataclass (:class:`UKF`,
:class:`LeastSquares`, :class:`E2E`, :class:`Policy`) and an entry in
:data:`METHODS`; :func:`config` turns the front door's keyword options into one (a
misspelt option lists the valid ones) and :func:`build` makes it a ready
:class:`Built` for a problem. Adding a method is one config class and one entry.
The configs and the table live in :mod:`jaxcal.calibrators.method_configs`, the
machinery behind :func:`build` in two modules, all re-exported here:

* :mod:`jaxcal.calibrators.model_based`: the UKF and least squares on the model
  ``F(w, theta_declared) -> x_used``; the measurement noise is the explicit input
  ``noise_std`` (the filter's covariance), the parameters are scaled by the
  half-width of the box and start at the nominal values. Their programs are
  compiled once per process (:mod:`jaxcal.calibrators.compiled`): the data, noise,
  prior and scales are arguments.
* :mod:`jaxcal.calibrators.learned`: the E2E network learns the inverse of the model
  from simulations over the box at the data's own operating conditions
  (:mod:`jaxcal.calibrators.e2e_sim`), or takes given weights; a trained policy is
  loaded from its run folder, gated by an absolute policy's run with ``anchor=``.

Every method is run by a jitted fleet runner with a sample check (non-finite
samples and samples outside the valid input box are skipped and flagged). A row
with some outputs missing is used by the UKF and least squares on its observed
outputs and skipped by E2E and a policy (reason ``x_partial``;
:mod:`jaxcal.calibrators.guard`).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.calibrators.learned import (
    e2e_calibrator,
    learned_built,
    make_runner,
    policy_calibrator,
)
from jaxcal.calibrators.method_configs import (
    E2E,
    METHODS,
    UKF,
    Built,
    LeastSquares,
    Policy,
    config,
    options_of,
)
from jaxcal.calibrators.model_based import (
    build_model_based,
    model_based_factory,
    model_check,
    model_inputs,
    state_scale,
    ukf_program,
)
from jaxcal.data.buckets import Buckets
from jaxcal.problem import Problem

__all__ = [
    "E2E",
    "METHODS",
    "UKF",
    "Built",
    "LeastSquares",
    "Policy",
    "build",
    "config",
    "make",
    "make_runner",
    "model_based_factory",
    "model_check",
    "model_inputs",
    "options_of",
    "state_scale",
    "ukf_program",
]


def build(problem: Problem, cfg, buckets: Buckets, seed: int = 0) -> Built:
    """:class:`Built` of the config ``cfg`` (:func:`config`) on ``problem``; ``buckets``
    are the data (E2E-sim trains on their conditions and float dtype)."""
    if isinstance(cfg, (UKF, LeastSquares)):
        return build_model_based(problem, cfg, buckets.dtype)
    if isinstance(cfg, E2E):
        from jaxcal.calibrators.policy import range_check  # E2E's own imports

        cal = e2e_calibrator(problem, buckets, seed, cfg)
        return learned_built(problem, cal, range_check(problem))
    cal, check = policy_calibrator(problem, cfg)
    return learned_built(problem, cal, check)


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
