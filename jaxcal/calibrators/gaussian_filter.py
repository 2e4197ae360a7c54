"""The Gaussian filter of the parameters (and hidden states): one skeleton, its
prediction given.

The UKF (:mod:`jaxcal.calibrators.ukf`) and the EKF
(:mod:`jaxcal.calibrators.methods.ekf`) filter the same state-space model::

    theta_t = theta_{t-1} + xi_t,        xi ~ N(0, Q),  Q = q^2 I
    (z_t, x_t) = step(z_{t-1}, w_t, theta_t) + (0, eps_t),   eps ~ N(0, R)

in the same units (outputs compared as ``(x - centre) / noise_std``, parameters as
``theta / theta_scale``, states as ``z / state_scale``; a static model is ``Z = 0``,
:func:`static_transition`) and differ only in how the prediction's moments are
taken: sigma points or a linearisation. :func:`make_gaussian_filter` is the rest, once:
the settings checked, the prior, the update on the observed outputs
(:func:`~jaxcal.calibrators.ukf_steps.update`), the projection of the mean into the
box, ``xhat`` and the step's ``aux``. A filter gives a :class:`Moments`: its
prediction, its prior of a model with memory and the covariance weights its update
takes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import (
    Calibrator,
    CalStepOutput,
    MeasureFn,
    Measurement,
    check_measurement,
    check_prior,
    check_scale,
    inner_box,
)
from jaxcal.calibrators.ukf_steps import UKFState, process_noise, step_aux, update
from jaxcal.problem import Transition
from jaxcal.typedefs import Array, PRNGKey


class Moments(NamedTuple):
    """How a filter takes the prediction's moments (module docstring).

    ``predict(state, propagate, noise, weights, num_states) -> _Prediction`` with
    ``propagate(a) -> (z_t / state_scale, normalised x_t)`` and ``noise = (q_theta,
    q_state)``; ``prior(at_rest, u0, cov_u, s_std, s_scale) -> UKFState`` the prior of
    a model with memory, ``at_rest(u) = init(w0, theta)``; ``weights(n, dtype) ->
    (wm, wc, spread)`` of the ``n``-dimensional state, ``wc`` what
    :func:`~jaxcal.calibrators.ukf_steps.update` reads."""

    predict: Callable
    prior: Callable
    weights: Callable


def static_transition(measure_fn: MeasureFn) -> Transition:
    """A static model ``F(w, theta) -> x`` as a transition without states (Z = 0)."""

    def init_state(w0, theta):
        del w0
        return jnp.zeros((0,), theta.dtype)

    def step(z, w, theta):
        return z, measure_fn(w, theta)

    return Transition(init_state, step, 0)


def make_gaussian_filter(
    moments: Moments,
    transition: Transition,
    cfg,
    measurement: Measurement,
    *,
    theta0: Array,
    theta_scale: Array | None = None,
    state_std: Array | None = None,
    state_q: Array | None = None,
    state_scale: Array | None = None,
    theta_box: tuple[Array, Array] | None = None,
    clip_points: bool = True,
) -> Calibrator:
    """The filter of ``moments`` as a ``Calibrator(init, step)``; the arguments are
    :func:`~jaxcal.calibrators.ukf.make_joint_ukf`'s (``cfg``: the filter's settings,
    with ``q``, ``r``, ``prior_std``, ``jitter``, ``posterior_xhat`` and
    ``return_cov``)."""
    measurement = check_measurement(measurement)
    centre, noise_std = measurement
    theta0, scale = check_prior(theta0, theta_scale)
    num_params = theta0.shape[0]
    init_state, step_fn, num_states = transition
    s_scale = check_scale(state_scale, num_states, theta0.dtype)
    s_std = state_vector(state_std, num_states, s_scale, "state_std")
    s_q = state_vector(state_q, num_states, 0.0 * s_scale, "state_q")
    weights = moments.weights(num_states + num_params, theta0.dtype)
    eye = jnp.eye(num_params, dtype=theta0.dtype)
    noise = process_noise(cfg, eye, s_q, s_scale)  # (q_theta, q_state)
    admissible = clip_to_box(theta_box if clip_points else None, theta0.dtype)
    project = project_mean(theta_box, scale, num_states)

    def unpack(a):
        return s_scale * a[:num_states], scale * a[num_states:]

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> UKFState:
        del key, x0  # the prior is fixed by the factory
        u0 = theta0 / scale
        cov_u = cfg.prior_std**2 * eye
        if not num_states:
            return UKFState(mean=u0, cov=cov_u)
        at_rest = lambda u: init_state(w0, admissible(scale * u))  # noqa: E731
        return moments.prior(at_rest, u0, cov_u, s_std, s_scale)

    def step(state: UKFState, w_t: Array, x_t: Array) -> tuple[UKFState, CalStepOutput]:
        def propagate(a: Array):
            z, theta = unpack(a)
            z_next, x = step_fn(z, w_t, admissible(theta))
            return z_next / s_scale, (x - centre) / noise_std

        pred = moments.predict(state, propagate, noise, weights, num_states)
        mean, cov, s_cov, innovation, log_lik = update(
            pred, x_t, measurement, weights, cfg.r
        )
        mean = project(mean)
        z_post, theta_post = unpack(mean)
        if cfg.posterior_xhat:  # x_t of the previous posterior state, new theta
            xhat = step_fn(unpack(state.mean)[0], w_t, admissible(theta_post))[1]
        else:  # the predicted measurement mean, free but one step behind the update
            xhat = centre + noise_std * pred.y_mean
        aux = step_aux(cfg, cov, s_cov, innovation, log_lik, z_post, scale, s_scale)
        out = CalStepOutput(theta=theta_post, xhat=xhat, aux=aux)
        return UKFState(mean=mean, cov=cov), out

    return Calibrator(init=init, step=step, accepts_partial=True)


def clip_to_box(theta_box: tuple[Array, Array] | None, dtype):
    """``theta -> theta`` clipped into ``theta_box``, the identity without a box."""
    if theta_box is None:
        return lambda theta: theta
    low, high = (jnp.asarray(b, dtype) for b in theta_box)
    return lambda theta: jnp.clip(theta, low, high)


def project_mean(theta_box: tuple[Array, Array] | None, scale: Array, num_states):
    """``a -> a`` with its scaled parameters ``a[Z:]`` clipped into ``theta_box``,
    a hair inside (:func:`~jaxcal.calibrators.interface.inner_box`); the identity
    without a box."""
    if theta_box is None:
        return lambda a: a
    low, high = inner_box(theta_box, scale)
    return lambda a: a.at[num_states:].set(jnp.clip(a[num_states:], low, high))


def state_vector(value, num_states: int, default: Array, field: str) -> Array:
    """A scalar or ``[Z]`` non-negative setting -> ``[Z]`` (``default`` if None)."""
    if value is None:
        return default
    arr = jnp.broadcast_to(jnp.asarray(value, default.dtype), (num_states,))
    if not isinstance(arr, jax.core.Tracer) and not np.all(np.asarray(arr) >= 0):
        raise ValueError(f"{field} must be >= 0 (scalar or [Z]), got {value}")
    return arr
