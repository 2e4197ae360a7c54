"""Sliding-window least squares for a model with memory: theta and the window's
initial state fitted by simulating the model over the window.

For ``(z_t, x_t) = step(z_{t-1}, w_t, theta)`` the window of the last ``N`` samples
is explained by the parameters *and* the state ``z_s`` the window starts from (the
moving-horizon estimate of Rao, Rawlings & Mayne 2003, with a constant theta over
the window and an arrival-cost prior on ``z_s``). Each step

1. advances ``z_s`` through the sample that leaves the window, with the current
   theta (the prior of the new window start, weight ``state_std``);
2. shifts the new sample in (time order: the model is simulated forwards);
3. runs ``num_iters`` Levenberg–Marquardt iterations on
   ``sum_i ||(x_i(theta, z_s) - x_i) / (noise_std r)||^2 + ||(z_s - z_prior) /
   state_std||^2 [+ ||(u - u_prev) / prior_std||^2]``, ``x_i`` simulated by ``lax.scan``
   and differentiated by ``jax.jacfwd`` over the ``P + Z`` unknowns; warm-started from
   the previous estimate. The iteration, its box projection and the covariance are the
   one solver core's (:mod:`jaxcal.numerics.levenberg_marquardt`).

A NaN in ``x_t`` is a missing output: it is left out of the residual (the sample's
other outputs still count), so the calibrator takes partial rows
(``Calibrator.accepts_partial``).

A static model is better served by :func:`~jaxcal.calibrators.methods.ls.window.
make_least_squares` (no scan, samples evaluated in parallel); the front picks it when
``Z = 0``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

from jaxcal.calibrators.interface import (
    Calibrator,
    CalStepOutput,
    Measurement,
    check_measurement,
    check_prior,
    check_scale,
)
from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig, damping_of
from jaxcal.calibrators.uncertainty.drift_std import (
    DriftHistory,
    drift_std,
    init_drift_history,
    prior_age,
)
from jaxcal.numerics.levenberg_marquardt import gauss_newton_cov, linearize, lm_run
from jaxcal.problem import Transition
from jaxcal.typedefs import Array, PRNGKey


@struct.dataclass
class WindowState:
    """Estimate plus the last ``window`` samples, oldest first."""

    u: Array  # [P] scaled parameters theta / theta_scale
    zs: Array  # [Z] state before the window's first sample (state units)
    w_buf: Array  # [N, Wd]
    x_buf: Array  # [N, S] (0 where an output was missing: the state stays finite)
    observed: Array  # [N, S] bool, False where an output was missing (NaN)
    valid: Array  # [N] bool, False until a slot holds a sample
    history: DriftHistory  # the past estimates the drift is measured from


def make_window_least_squares(
    transition: Transition,
    cfg: LeastSquaresConfig,
    measurement: Measurement,
    *,
    theta0: Array,
    theta_scale: Array | None = None,
    state_std: Array | None = None,
    state_scale: Array | None = None,
    theta_box: tuple[Array, Array] | None = None,
) -> Calibrator:
    """The moving-window least-squares calibrator of a stateful model.

    Args:
        transition: ``Transition(init, step, Z)`` (``Problem.transition()``):
            ``init(w0, theta [P]) -> z0 [Z]``, ``step(z, w, theta [P]) -> (z', x
            [S])``, differentiable.
        cfg: window, iterations, noise ``r`` and the optional theta prior.
        measurement: the outputs' ``noise_std [S]`` (times ``cfg.r``) is the
            residual unit; ``centre`` is not used.
        theta0: ``[P]`` initial estimate; theta_scale: ``[P]`` scales.
        state_std: ``[Z]`` (or scalar) std of the window-start state around its
            propagated value (the arrival cost); default ``state_scale``.
        state_scale: ``[Z]`` natural size of each state (default ones).
        theta_box: ``(low [P], high [P])``: each LM step is projected onto it (a
            window without excitation leaves a direction unobserved; the projection
            keeps the estimate where the model is defined).

    Returns:
        ``Calibrator(init, step)``; ``aux`` holds ``theta_std [P]`` (Laplace,
        widened by the window's lag behind a drifting theta:
        :func:`~jaxcal.calibrators.uncertainty.drift_std.drift_std`), ``laplace_std
        [P]``, ``cost []``, ``state [Z]`` (the state after the sample, simulated over
        the window) and ``state_std [Z]`` (of the window start).
    """
    measurement = check_measurement(measurement)
    theta0, scale = check_prior(theta0, theta_scale)
    num_params = theta0.shape[0]
    init_state, step_fn, num_states = transition
    s_scale = check_scale(state_scale, num_states, theta0.dtype)
    s_std = _arrival_std(state_std, s_scale)
    sigma = measurement.noise_std * cfg.r  # residual unit: one noise std
    box = _parameter_box(theta_box, scale, num_states)
    simulate = functools.partial(_simulate, step_fn)

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> WindowState:
        del key
        return _initial_window(init_state, cfg.window, theta0, scale, w0, x0)

    def step(state: WindowState, w_t: Array, x_t: Array):
        window = _advance(step_fn, state, scale, w_t, x_t)  # .zs: the start's prior
        used = window.valid[:, None] & window.observed  # [N, S] the cost's residuals
        residual = _window_residual(simulate, window, used, cfg, sigma, scale, s_std)
        v0 = jnp.concatenate([state.u, jnp.zeros((num_states,), state.u.dtype)])
        fit = lm_run(linearize(residual), v0, cfg.num_iters, damping_of(cfg), box=box)
        u, dz = fit.y[:num_params], fit.y[num_params:]
        zs = window.zs + s_std * dz
        theta = scale * u
        pred, z_end = simulate(theta, zs, window.w_buf, window.valid)
        cov = gauss_newton_cov(fit.jac)
        std = jnp.sqrt(jnp.diagonal(cov))

        def simulate_path(path):  # the outputs along a theta path [N, P]
            return simulate(path, zs, window.w_buf, window.valid)[0]

        theta_std, laplace_std, history = _drift_widened_std(
            fit, u, cov, simulate_path, used, sigma, scale, state.history, cfg,
            num_states,
        )  # fmt: skip
        aux = {
            "theta_std": scale * theta_std,
            "laplace_std": scale * laplace_std,
            "cost": fit.cost,
            "state": z_end,
            "state_std": s_std * std[num_params:],
        }
        new_state = window.replace(u=u, zs=zs, history=history)
        return new_state, CalStepOutput(theta=theta, xhat=pred[-1], aux=aux)

    return Calibrator(init=init, step=step, accepts_partial=True)


def _arrival_std(state_std, s_scale: Array) -> Array:
    """``[Z]`` std of the window start around its propagated value (the arrival
    cost): ``state_std`` broadcast, default the states' natural size."""
    if state_std is None:
        return s_scale
    return jnp.broadcast_to(jnp.asarray(state_std, s_scale.dtype), s_scale.shape)


def _parameter_box(theta_box, scale: Array, num_states: int):
    """The LM iteration's box on ``[u, dz]``: ``theta_box`` on the scaled parameters;
    the window-start state is free (``None``: no box)."""
    if theta_box is None:
        return None
    free = jnp.full((num_states,), jnp.inf, scale.dtype)
    low, high = (jnp.asarray(b, scale.dtype) / scale for b in theta_box)
    return (jnp.concatenate([low, -free]), jnp.concatenate([high, free]))


def _simulate(step_fn, theta, zs, w_buf, valid):
    """Outputs ``[N, S]`` over the window and the final state from ``zs``; invalid
    slots hold z. ``theta`` is ``[P]`` or one per sample, ``[N, P]``."""
    thetas = jnp.broadcast_to(theta, w_buf.shape[:1] + theta.shape[-1:])

    def body(z, inputs):
        w, ok, theta_k = inputs
        z_next, x = step_fn(z, w, theta_k)
        return jnp.where(ok, z_next, z), x

    z_end, x = lax.scan(body, zs, (w_buf, valid, thetas))
    return x, z_end


def _initial_window(init_state, window: int, theta0, scale, w0, x0) -> WindowState:
    """The state before the first sample: the estimate at ``theta0``, the window
    starting from ``init(w0, theta0)``; unfilled slots hold the first sample so the
    model is never run at zeros."""
    return WindowState(
        u=theta0 / scale,
        zs=jnp.asarray(init_state(w0, theta0), theta0.dtype),
        w_buf=jnp.tile(w0, (window, 1)),
        x_buf=jnp.tile(jnp.nan_to_num(x0), (window, 1)),
        observed=jnp.ones((window, x0.shape[0]), bool),
        valid=jnp.zeros((window,), bool),
        history=init_drift_history(theta0 / scale, window),
    )


def _advance(step_fn, state: WindowState, scale, w_t: Array, x_t: Array):
    """The window once ``(w_t, x_t)`` entered, as a :class:`WindowState` whose ``zs``
    is the prior of its start: the oldest sample leaves (the start advanced through
    it with the current theta), the new one shifts in (oldest first: the model is
    simulated forwards); a missing output is 0 in ``x_buf`` and False in
    ``observed``."""
    theta_now = scale * state.u
    z_left, _ = step_fn(state.zs, state.w_buf[0], theta_now)
    zs_prior = jnp.where(state.valid[0], z_left, state.zs)
    w_buf = jnp.concatenate([state.w_buf[1:], w_t[None]])
    observed_t = ~jnp.isnan(x_t)  # a missing output leaves the residual
    x_buf = jnp.concatenate([state.x_buf[1:], jnp.where(observed_t, x_t, 0.0)[None]])
    observed = jnp.concatenate([state.observed[1:], observed_t[None]])
    valid = jnp.concatenate([state.valid[1:], jnp.ones((1,), bool)])
    return state.replace(
        zs=zs_prior, w_buf=w_buf, x_buf=x_buf, observed=observed, valid=valid
    )


def _window_residual(simulate, window: WindowState, used, cfg, sigma, scale, s_std):
    """The residual of ``v = [u, dz]`` (scaled parameters, the window start's offset
    from its prior in ``state_std``): the used outputs in noise stds, the arrival
    cost ``z_s ~ N(z_prior, state_std^2)`` and, with ``prior_std``, the step from
    the previous estimate ``window.u``."""
    num_params, u_prev = window.u.shape[0], window.u

    def residual(v):
        u, dz = v[:num_params], v[num_params:]
        zs = window.zs + s_std * dz
        pred, _ = simulate(scale * u, zs, window.w_buf, window.valid)
        r = jnp.where(used, (pred - window.x_buf) / sigma, 0.0).ravel()
        r = jnp.concatenate([r, dz])  # arrival cost: z_s ~ N(z_prior, std^2)
        if cfg.prior_std is not None:
            r = jnp.concatenate([r, (u - u_prev) / cfg.prior_std])
        return r

    return residual


def _drift_widened_std(
    fit, u, cov, simulate_path, used, sigma, scale, history, cfg, num_states: int
):
    """``(theta_std, laplace_std, history)`` of :func:`drift_std`: the Laplace std
    widened by the window's lag behind a drifting theta.

    The residual's response to theta drifting within the window goes through the
    simulated state (``simulate_path(theta [N, P]) -> x [N, S]``: the model's memory
    spreads a drift over later samples); the arrival cost has no theta in it; the
    prior on theta is pseudo-data of the previous estimate's age.
    """
    num_params, num_outputs = u.shape[0], used.shape[1]
    age = jnp.arange(cfg.window - 1, -1, -1).astype(u.dtype)

    def drifted(rate):
        path = scale * (u[None] - age[:, None] * rate[None])  # [N, P]
        return jnp.where(used, simulate_path(path) / sigma, 0.0).ravel()

    drift_jac = [
        jax.jacfwd(drifted)(jnp.zeros_like(u)),
        jnp.zeros((num_states, num_params), u.dtype),
    ]
    if cfg.prior_std is not None:
        prior_rows = jnp.diag(prior_age(history)) / cfg.prior_std
        drift_jac.append(-prior_rows)
    ages = jnp.concatenate([  # the rows' sample ages; -1: no sample
        jnp.repeat(age, num_outputs),
        jnp.full(fit.jac.shape[0] - age.size * num_outputs, -1.0, u.dtype),
    ])  # fmt: skip
    return drift_std(
        history, u, cov, fit.jac, jnp.concatenate(drift_jac), ages, cfg.window
    )
