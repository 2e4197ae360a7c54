"""Incremental actions: the policy as a learned feedback on the tracking residual.

The paper's policy outputs theta itself (``action_to_theta``: an affine map of the
action box), so its resolution is that of a function approximator: on noise-free
data it stops an order of magnitude or more above the exact filter, whatever the
training budget (the E2E network, trained with labels, stops at the same level).
Here the action is a *change* of theta driven by the model's prediction error, as in
a controller with integral action, predict then correct:

    x-hat_t = F(w_t, theta_{t-1}),  r_t = (x_t - x-hat_t) / sigma_x     [S]
    s_t   = [r_t / |r_t|, lg |r_t|, norm(w_t), theta_{t-1} in [-1, 1]]
    theta_t = clip(theta_{t-1} + M * a_t * |r_t| / (|r_t| + n_ref), box)

with |r| the RMS of r over the outputs, M the largest step (``max_increment`` of
the box width) and n_ref = 0.5 * J * M, J the RMS sensitivity of the normalised
outputs to each parameter (:func:`sensitivity`). The gate |r| / (|r| + n_ref) makes
the change exactly zero when the model predicts the data, so a fixed point of the
closed loop is a point of zero prediction error whatever small offset the network has
at zero input; far from it the step saturates at M. With the gate, an action of
about 0.5 is a Gauss-Newton step for small errors. The direction r / |r| and the
logarithm of |r| keep the network's input of order one from an error of 1e-8 to 1.

theta_t answers sample t itself (no lag: a jump of theta between flights is
corrected on the sample that shows it), and a step costs one model evaluation, the
prediction, as the absolute policy's. The training cost of the action is the
prediction error of the next sample, F(w_{t+1}, theta_t), the same evaluation that
gives the next state. A model with memory advances its state with theta_{t-1}, the
value the prediction used (theta moves slowly; a second evaluation per sample would
be exact).

With ``EnvConfig.gauss_newton`` the observation also holds the residual's
Gauss-Newton step through the model's Jacobian, scaled so that an action equal to it
is that step, and the stream's age (:func:`gauss_newton_features`); the Jacobian
costs P forward-mode tangents of the same evaluation, and on a model with memory it
carries the state's sensitivity (:func:`step_with_sensitivity`). The network then
learns a gain schedule rather than the model's inverse. With ``EnvConfig.gn_filter``
it also holds the step of an extended Kalman filter on theta carried along the
stream (:func:`filter_feature`): one sample's step cannot separate parameters the
outputs see in one direction only (a battery's one voltage), the samples together
can, and the filter's gain falls as its data grow, as the UKF's does.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.numerics.small_solve import spd_solve
from jaxcal.typedefs import Array

# |r| below this counts as zero in the direction r / |r| (float32 observations)
_TINY = 1e-12
# samples since a stream's start beyond which its age no longer changes the
# observation (the start-up transient is over; training windows are longer)
AGE_HORIZON = 32
# The filter step's random walk per sample and prior std, in half-box units: the
# UKF's defaults (jaxcal.calibrators.ukf_steps.UKFConfig.q, .prior_std), so that a
# gain of 1 on it starts and settles as the filter it is compared with.
FILTER_Q = 0.01
FILTER_PRIOR_STD = 1.0


def residual_features(resid: Array) -> tuple[Array, Array]:
    """``(r / |r|, lg-scaled |r|)`` of a normalised residual ``[S]``.

    ``|r|`` is the RMS over the outputs; the log is mapped so that |r| = 1e-8 .. 1
    spans [-2, 2] (clipped outside).
    """
    norm = jnp.sqrt(jnp.mean(jnp.square(resid)))
    direction = resid / (norm + _TINY)
    log_norm = jnp.clip((jnp.log10(norm + _TINY) + 4.0) / 2.0, -3.0, 3.0)
    return direction, log_norm[None]


def increment_observation(
    resid: Array,
    w_next_norm: Array,
    theta: Array,
    low: Array,
    high: Array,
    extra: Array | None = None,
) -> Array:
    """``s = [r / |r|, lg |r|, norm(w_{t+1}), theta_t in [-1, 1]]`` as float32
    ``[S + 1 + W + P]``, followed by ``extra`` (:func:`gauss_newton_features`)
    where given."""
    direction, log_norm = residual_features(resid)
    theta_unit = 2.0 * (theta - low) / (high - low) - 1.0
    parts = [direction, log_norm, w_next_norm, theta_unit]
    obs = jnp.concatenate(parts if extra is None else [*parts, extra])
    return obs.astype(jnp.float32)


def gauss_newton_features(
    resid, jac, age, params, max_increment: float, *, one_sample=True, filtered=None
) -> Array:
    """``[P + 1]``: the Gauss-Newton step of the residual (:func:`gauss_newton_feature`)
    and the stream's age, ``log(1 + min(n, H)) / log(1 + H)`` in [0, 1] for ``n``
    samples since its start (H = :data:`AGE_HORIZON`): a Kalman filter's gain falls
    as its data grow, so the start-up transient wants larger steps than the steady
    state. ``params``: anything with ``x_std``, ``theta_low``, ``theta_high`` and
    ``step_ref`` (the environment's or the deployed policy's). ``filtered``: the
    filter's step ``[P]`` (:func:`filter_feature`), placed before the age;
    ``one_sample=False`` leaves out the one-sample step (``[P + 1]`` then holds the
    filter's step and the age)."""
    parts = []
    if one_sample:
        parts.append(
            gauss_newton_feature(
                resid, jac, params.x_std, params.theta_low, params.theta_high,
                max_increment, params.step_ref,
            ).astype(jnp.float32)
        )  # fmt: skip
    if filtered is not None:
        parts.append(filtered.astype(jnp.float32))
    n = jnp.minimum(jnp.asarray(age, jnp.float32), AGE_HORIZON)
    old = jnp.log1p(n) / np.log1p(AGE_HORIZON)
    return jnp.concatenate([*parts, old[None]])


def initial_filter_cov(
    param_dim: int, dtype, prior_std: float = FILTER_PRIOR_STD
) -> Array:
    """A stream's first filter covariance ``[P, P]`` in half-box units (the UKF's
    prior: ``prior_std``, default :data:`FILTER_PRIOR_STD`)."""
    return prior_std**2 * jnp.eye(param_dim, dtype=dtype)


def filter_feature(
    cov: Array,
    resid: Array,
    jac: Array,
    params,
    max_increment: float,
    q: float = FILTER_Q,
    whole: bool = False,
    noise_scale: Array | None = None,
) -> tuple[Array, Array]:
    """``(cov', step [P])``: one extended Kalman filter update of theta, its step
    in the action's scale (as :func:`gauss_newton_feature`'s).

    The filter runs in half-box units ``u = theta / h`` (``h = (high - low) / 2``,
    the UKF's ``theta_scale``) with a random walk ``q`` per sample (default
    :data:`FILTER_Q`, the UKF's) and
    the noise ``params.x_noise`` ``[S]`` (output units; what the training passes,
    ``jaxcal.training.data.train_env.training_env_params``):
    ``P- = P + q^2 I``, ``S = J P- J^T + R``, ``K = P- J^T S^-1``, the step ``K r``
    and ``P = (I - K J) P- (I - K J)^T + K R K^T`` (the Joseph form, which keeps
    ``P`` symmetric positive definite in float32), Särkkä (2013), "Bayesian
    Filtering and Smoothing", alg. 5.4. ``J`` is the prediction's Jacobian
    ``jac`` ``[S, P]`` and ``r`` the raw residual ``resid * x_std``. The filter's
    mean is the policy's theta: the step is the filter's from where the policy is.
    ``noise_scale`` ``[S]``: each output's noise variance is taken ``max(1,
    noise_scale)`` times its own (:func:`adapted_noise_scale`); ``None``: as given.
    """
    half = 0.5 * (params.theta_high - params.theta_low)
    j = (jac * half[None, :]).astype(cov.dtype)
    eye = jnp.eye(cov.shape[0], dtype=cov.dtype)
    pred = cov + q**2 * eye
    variance = jnp.square(params.x_noise)
    if noise_scale is not None:
        variance = variance * jnp.maximum(noise_scale, 1.0)
    noise = jnp.diag(variance.astype(cov.dtype))
    s = j @ pred @ j.T + noise
    gain = spd_solve(s, j @ pred).T  # S symmetric: P- J^T S^-1
    keep = eye - gain @ j
    new_cov = keep @ pred @ keep.T + gain @ noise @ gain.T
    new_cov = 0.5 * (new_cov + new_cov.T)
    delta = half * (gain @ (resid * params.x_std).astype(cov.dtype))
    return new_cov, step_feature(delta, resid, params, max_increment, whole)


def adapted_noise_scale(scale: Array, resid: Array, jac: Array, params, horizon: int):
    """``[S]`` each output's noise variance over its declared one, as the
    innovations show it, updated by one sample (the filter's adaptive measurement
    noise; Mehra (1972), "Approaches to adaptive filtering", IEEE TAC 17(5)).

    Only the part of the innovation no change of theta explains is read: with the
    whitened innovation ``e = r / sigma`` and Jacobian ``A = J / sigma``, its
    least-squares remainder ``e_perp = (I - A (A^T A)^-1 A^T) e`` has
    ``E[e_perp_k^2] = (1 - h_k) v_k`` for an output of noise variance ``v_k``
    declared ones (``h_k`` the leverage, ``diag A (A^T A)^-1 A^T``), whatever theta
    does, so a parameter that moves fast (a fault) does not read as noise. A bias,
    a drift or a gain error on one output shows in it (the others cannot follow),
    and the filter weighs that output less as its ``v`` grows:
    ``v <- v + (e_perp^2 - (1 - h) v) / horizon``, an exponential average over
    ``horizon`` samples. Where the outputs are no more than the parameters the
    remainder is zero and ``v`` stays where it is (nothing to compare with).
    ``resid`` is the normalised innovation ``(x - x-hat) / x_std`` ``[S]``, ``jac``
    ``[S, P]`` the prediction's Jacobian in output units; ``params`` as
    :func:`filter_feature`'s.
    """
    sigma = params.x_noise.astype(jac.dtype)
    a = jac * (0.5 * (params.theta_high - params.theta_low))[None, :] / sigma[:, None]
    e = (resid * params.x_std).astype(jac.dtype) / sigma
    gram = a.T @ a
    damping = 1e-9 * jnp.trace(gram) / a.shape[1] + 1e-30
    solve = spd_solve(
        gram + damping * jnp.eye(a.shape[1], dtype=a.dtype),
        jnp.concatenate([a.T, (a.T @ e)[:, None]], axis=1),
    )
    leverage = jnp.clip(jnp.sum(a * solve[:, :-1].T, axis=1), 0.0, 1.0)
    remainder = e - a @ solve[:, -1]
    scale = scale.astype(jac.dtype)
    new = scale + (jnp.square(remainder) - (1.0 - leverage) * scale) / horizon
    return jnp.clip(new, 1e-3, 1e6).astype(resid.dtype)


def initial_noise_scale(filtered: bool, adapt: int, num_states: int, like: Array):
    """The adaptive filter's noise scale before a stream's first sample (ones like
    ``like``: the declared noise), ``None`` where it does not adapt: no filter, no
    ``adapt`` horizon, or the filter not on theta alone (a model with memory). The
    one rule of the training environment and the deployed step."""
    if not (filtered and adapt) or num_states:
        return None
    return jnp.ones_like(like)


def step_feature(delta, resid, params, max_increment: float, whole: bool) -> Array:
    """``[P]`` a filter's step ``delta`` (theta units) in the action's scale, so that
    a unit gain on it takes that step through the gated increment."""
    norm = jnp.sqrt(jnp.mean(jnp.square(resid)))
    # The gated increment takes a share |r| / (|r| + n_ref) of the largest step:
    # ``whole`` divides that gate out, so that a unit gain on the feature is the
    # filter's step at any residual; without it (the runs before it) the feature
    # inverts the gate's small-residual slope |r| / n_ref only, and a parameter
    # with a small n_ref (the battery's capacity, 9e-4) took a hundredth of it
    gate = norm + params.step_ref if whole else params.step_ref
    scale = gate / (
        max_increment * (params.theta_high - params.theta_low) * (norm + _TINY)
    )
    return jnp.clip(delta * scale, -10.0, 10.0)


def gauss_newton_feature(
    resid: Array,
    jac: Array,
    x_std: Array,
    low: Array,
    high: Array,
    max_increment: float,
    step_ref: Array,
) -> Array:
    """``[P]`` the Gauss-Newton step of the residual in the action's own scale.

    With ``J = d(x / sigma_x) / d theta`` at the prediction (``jac`` ``[S, P]`` in
    output units over ``x_std``), the step that explains the normalised residual
    ``r`` is ``delta = (J^T J + lambda I)^-1 J^T r`` (Levenberg's damping ``lambda``
    a millionth of the mean curvature, so an unseen parameter gets no step rather
    than an infinite one). The gated increment moves theta by
    ``M (high - low) a |r| / (|r| + n_ref)``, about ``M (high - low) a |r| / n_ref``
    for small residuals, so ``a = g delta n_ref / (M (high - low) |r|)`` is the
    Gauss-Newton step with gain ``g``: that ratio is the feature, clipped to
    [-10, 10]. The network then learns a gain per parameter and situation (a
    Kalman-like gain) instead of the model's inverse, which its fixed-size input
    cannot resolve as precisely (``results/policy_any_model``).
    """
    j = jac / x_std[:, None]
    curvature = j.T @ j
    damping = 1e-6 * jnp.trace(curvature) / j.shape[1] + 1e-30
    delta = spd_solve(
        curvature + damping * jnp.eye(j.shape[1], dtype=j.dtype), j.T @ resid
    )
    norm = jnp.sqrt(jnp.mean(jnp.square(resid)))
    scale = step_ref / (max_increment * (high - low) * (norm + _TINY))
    return jnp.clip(delta * scale, -10.0, 10.0)


def step_with_sensitivity(step, z, theta: Array, sens: Array | None):
    """``(J [S, P], sens', *out)`` of one model step ``step(z, theta) -> (z', x-hat,
    ...)`` with its Jacobian in theta by forward mode (P tangents: a few parameters).

    A model with memory carries ``sens = dz / dtheta`` ``[Z, P]`` (forward
    sensitivity, as the extended Kalman filter's joint state: the state moved with
    theta over the past samples, theta held): J is then the total derivative
    ``dx-hat / dtheta + dx-hat / dz sens`` and ``sens'`` the next state's. With a
    one-step Jacobian, a parameter that acts through the state (a motor's winding
    resistance through its speed) looks several times weaker than it is and the
    Gauss-Newton step comes out too short. A static model passes ``sens=None``
    (``sens'`` is ``None``).
    """

    def moved(th):
        z_in = z if sens is None else z + sens @ (th - theta).astype(sens.dtype)
        out = step(z_in, th)
        return (out[1] if sens is None else (out[0], out[1])), out

    jac, out = jax.jacfwd(moved, has_aux=True)(theta)
    if sens is None:
        return (jac, None, *out)
    return (jac[1], jac[0], *out)


def apply_increment(
    action: Array,
    theta: Array,
    resid: Array,
    low: Array,
    high: Array,
    max_increment: float,
    step_ref: Array,
) -> Array:
    """theta + M a |r| / (|r| + n_ref), clipped into the box (see the module doc).

    Args:
        action: ``[P]`` squashed action in [-1, 1] (clipped).
        theta: ``[P]`` current theta.
        resid: ``[S]`` normalised residual of the current sample.
        low, high: ``[P]`` box.
        max_increment: M as a share of the box width.
        step_ref: ``[P]`` n_ref, the residual RMS at which the gate is 1/2.
    """
    norm = jnp.sqrt(jnp.mean(jnp.square(resid)))
    gate = norm / (norm + step_ref)
    step = max_increment * (high - low) * jnp.clip(action, -1.0, 1.0) * gate
    return jnp.clip(theta + step.astype(theta.dtype), low, high)


def sensitivity(
    measure, inputs, theta: np.ndarray, x_std: np.ndarray, step: np.ndarray
) -> np.ndarray:
    """J_p: RMS over samples and outputs of d(x / sigma_x) / d theta_p (host-side).

    Central differences of ``measure(row, theta [P]) -> x [S]`` (one vmapped call
    per parameter and sign) at the given samples, ``step`` ``[P]`` per parameter: a
    finite difference rather than ``jvp`` so that any dynamics callable works (a
    surrogate, a solver without a tangent rule).

    Args:
        measure: the model's outputs at (one row of ``inputs``, theta).
        inputs: a pytree of ``[N, ...]`` arrays (conditions, ...); theta: ``[P]``
            where the slope is taken.
        x_std: ``[S]`` output scale; step: ``[P]`` difference step.

    Returns:
        ``[P]`` positive sensitivities (a parameter the outputs do not see gets the
        smallest positive one of the others, or 1).
    """
    theta = jnp.asarray(theta)
    batched = jax.jit(jax.vmap(measure, in_axes=(0, None)))
    out = []
    for p in range(theta.shape[0]):  # P calls at set-up, not a hot path
        up = theta.at[p].add(step[p])
        down = theta.at[p].add(-step[p])
        slope = (
            np.asarray(batched(inputs, up)) - np.asarray(batched(inputs, down))
        ) / (2.0 * step[p])
        out.append(np.sqrt(np.mean(np.square(slope / np.asarray(x_std)))))
    sens = np.asarray(out, np.float64)
    good = np.isfinite(sens) & (sens > 0)
    fill = sens[good].min() if good.any() else 1.0
    return np.where(good, sens, fill)


def increment_step_ref(
    dyn, params, theta: np.ndarray, max_increment: float, samples: int = 256
) -> np.ndarray:
    """n_ref = 0.5 J M per parameter (:mod:`jaxcal.envs.increment`): J the RMS
    sensitivity of the normalised outputs at ``theta`` over ``samples`` training rows
    spread evenly over the valid rows, M the largest step."""
    lengths = np.asarray(params.lengths)
    units, times = np.nonzero(np.arange(params.x.shape[1])[None] < lengths[:, None])
    pick = np.linspace(0, units.size - 1, min(samples, units.size)).astype(int)
    u, t = units[pick], times[pick]
    inputs = (
        params.w[u, t],
        params.x[u, t],
        None if params.z_ref is None else params.z_ref[u, t],
    )

    def measure(row, th):
        w1, x1, z1 = row
        return dyn.step(params.dyn_params, z1, w1, x1, th.astype(x1.dtype))[1]

    width = np.asarray(params.theta_high - params.theta_low, np.float64)
    theta = np.clip(
        np.asarray(theta, np.float64),
        np.asarray(params.theta_low) + 1e-3 * width,
        np.asarray(params.theta_high) - 1e-3 * width,
    )
    sens = sensitivity(measure, inputs, theta, np.asarray(params.x_std), 1e-3 * width)
    return 0.5 * sens * max_increment * width
