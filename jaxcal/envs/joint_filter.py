"""The filter step of a model with memory: an extended Kalman filter on the state and
theta together.

On a model with memory (``z_t = f(z_{t-1}, w_t, theta_t)``, ``x_t = h(...)``) the
policy's filter (``EnvConfig.gn_filter`` with ``filter_whole``) carries the joint
covariance ``C`` ``[Z + P, Z + P]`` of the state (its own units) and theta (half-box
units ``u = theta / h``), as the UKF does with its sigma points. Carrying only the
state's sensitivity ``dz / dtheta`` (theta held over the past) is not the same: with
theta a random walk it overstates how much the current theta made the state and
leaves out the spread of the state that past theta noise built
(``results/policy_any_model``, "Under model error").

One update at sample t, from the state after t-1 and the policy's theta (the filter's
mean: the step is the filter's from where the policy is), Särkkä (2013), "Bayesian
Filtering and Smoothing", sec. 5.2 with the measurement taken at the transition:

* ``C- = C + diag(0, q^2 I)`` (theta's random walk enters sample t);
* ``M = [[A_z, A_u], [0, I]]``, ``H = [H_z, H_u]``: the step's Jacobians in
  ``(z_{t-1}, u_t)`` (:func:`step_with_joint`);
* ``S = H C- H^T + R``, ``K = M C- H^T S^-1``, ``(dz, du) = K r``,
  ``C' = M C- M^T - K S K^T``.

The state after t is ``z_t + dz`` when theta moves by ``du``; when the policy moves it
otherwise (a trained correction, the box), the state follows the posterior
regression on theta, ``C'_zu C'_uu^-1`` (:func:`conditioned_state`): the untrained
policy (gain 1) is exactly this filter.

The update's products of two 4-wide matrices (a reactor's two states and two
parameters) are written out (:func:`_product`): XLA's CPU runtime runs such a dot as
a call to Eigen per matrix, and over a fleet (``vmap`` over units) as one call per
unit, which dominates a small model's cost per row
(``results/bench/stream_profile.md``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcal.envs.increment import step_feature
from jaxcal.numerics.small_solve import spd_solve
from jaxcal.typedefs import Array


def initial_joint_cov(num_states: int, param_dim: int, dtype, prior_std: float):
    """``[Z + P, Z + P]``: the state known (the stream's reference state), theta
    at ``prior_std`` half-widths."""
    diag = jnp.concatenate(
        [jnp.zeros(num_states, dtype), jnp.full(param_dim, prior_std**2, dtype)]
    )
    return jnp.diag(diag)


def joint_prior(dyn, dyn_params, w0: Array, theta0: Array, cov: Array, half: Array):
    """``[Z + P, Z + P]``: a joint filter's first covariance with the first state's
    dependence on theta: the state ``init_at(w0, theta)`` moves with theta by
    ``S = dz / du`` (forward mode, ``u = theta / half``), so theta's prior
    ``C_uu`` (``cov``'s theta block) gives the state ``S C_uu S^T`` and the cross
    term ``S C_uu``, the linearised form of the UKF's joint prior
    (:func:`~jaxcal.calibrators.ukf_steps.joint_prior`). Without them the filter
    took the first state as known and read its error as theta's (the reactor,
    untrained: 1.54x the UKF's theta error). ``cov`` as it is where the dynamics
    cannot say (``dyn.init_at`` is ``None``)."""
    if getattr(dyn, "init_at", None) is None:
        return cov
    num_states = dyn.num_states

    def first(u):
        theta = theta0 + (u * half).astype(theta0.dtype)
        return dyn.init_at(dyn_params, w0, theta).astype(cov.dtype)

    sens = jax.jacfwd(first)(jnp.zeros(theta0.shape, cov.dtype))  # [Z, P]
    c_uu = cov[num_states:, num_states:]
    cross = sens @ c_uu
    return jnp.block([[cross @ sens.T, cross], [cross.T, c_uu]])


def step_with_joint(step, z: Array, theta: Array, sens: Array, half: Array):
    """``(J [S, P], sens' [Z, P], (A [Z, n], H [S, n]), *out)`` of one model step
    ``step(z, theta) -> (z', x-hat, ...)``, its Jacobians in ``(z, u)`` by forward
    mode (``n = Z + P`` tangents). ``J`` and ``sens'`` are
    :func:`~jaxcal.envs.increment.step_with_sensitivity`'s (the one-sample
    Gauss-Newton observation reads them)."""
    num_states = z.shape[0]

    def moved(v):
        dz, du = v[:num_states], v[num_states:]
        out = step(z + dz.astype(z.dtype), theta + (du * half).astype(theta.dtype))
        return (out[0], out[1]), out

    v0 = jnp.zeros(num_states + theta.shape[0], theta.dtype)
    (a, h), out = jax.jacfwd(moved, has_aux=True)(v0)
    a_z, a_theta = a[:, :num_states], a[:, num_states:] / half[None, :]
    h_z, h_theta = h[:, :num_states], h[:, num_states:] / half[None, :]
    sens = sens.astype(a.dtype)
    return (h_theta + h_z @ sens, a_z @ sens + a_theta, (a, h), *out)


def joint_filter_feature(
    cov, resid, joint, params, max_increment: float, q: float, state_walk=None,
    noise_scale=None,
):  # fmt: skip
    """``(C', feature [P], dz [Z], du [P])``: the update of the module docstring, the
    theta step in the action's scale (:func:`~jaxcal.envs.increment.step_feature`,
    the gate divided out). ``state_walk`` ``[Z]``: the state's random walk per
    sample (none by default; the output biases', :mod:`jaxcal.envs.bias_states`);
    ``noise_scale`` ``[S]``: each output's noise variance taken ``max(1, scale)``
    times its own (:func:`~jaxcal.envs.increment.adapted_noise_scale`)."""
    a, h = (m.astype(cov.dtype) for m in joint)
    num_states, n = a.shape[0], cov.shape[0]
    param_dim = n - num_states
    if state_walk is None:
        state_walk = jnp.zeros(num_states, cov.dtype)
    walk = jnp.concatenate(
        [state_walk.astype(cov.dtype), jnp.full(param_dim, q**2, cov.dtype)]
    )
    pred = cov + jnp.diag(walk)
    lower = jnp.concatenate(
        [
            jnp.zeros((param_dim, num_states), cov.dtype),
            jnp.eye(param_dim, dtype=cov.dtype),
        ],
        axis=1,
    )
    m = jnp.concatenate([a, lower], axis=0)
    variance = jnp.square(params.x_noise)
    if noise_scale is not None:
        variance = variance * jnp.maximum(noise_scale, 1.0)
    noise = jnp.diag(variance.astype(cov.dtype))
    s = _product(h, pred) @ h.T + noise
    m_pred = _product(m, pred)
    gain = spd_solve(s, _product(h, m_pred.T)).T
    new_cov = _product(m_pred, m.T) - gain @ s @ gain.T
    new_cov = 0.5 * (new_cov + new_cov.T)
    d = gain @ (resid * params.x_std).astype(cov.dtype)
    dz, du = d[:num_states], d[num_states:]
    half = 0.5 * (params.theta_high - params.theta_low)
    feature = step_feature(half * du, resid, params, max_increment, True)
    return new_cov, feature, dz, du


# the longest contraction written out (:func:`_product`): the joint filter's states
# plus parameters (the reactor's 2 + 2)
_WRITTEN_OUT = 4


def _product(a: Array, b: Array) -> Array:
    """``a @ b`` for a contraction of at most :data:`_WRITTEN_OUT` terms, written
    out as a sum of outer products so that it fuses with its neighbours (the module
    docstring); a longer one is the dot. Its rounding is not the dot's to the bit
    (the dot's summation order is Eigen's): the training environment and the
    deployed step both call this one function, so they agree with each other."""
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] > _WRITTEN_OUT:
        return a @ b
    out = a[:, 0, None] * b[None, 0, :]
    for k in range(1, a.shape[1]):  # unrolled at trace time: 2-4 terms
        out = out + a[:, k, None] * b[None, k, :]
    return out


def conditioned_state(z: Array, cov: Array, du_taken: Array, du_filter: Array):
    """The state after the policy's step ``du_taken`` (half-box units) where the
    filter's was ``du_filter``: ``z + C_zu C_uu^-1 (du_taken - du_filter)``."""
    num_states = z.shape[0]
    c_uu, c_uz = cov[num_states:, num_states:], cov[num_states:, :num_states]
    regress = spd_solve(c_uu, c_uz).T  # C_zu C_uu^-1 (C symmetric)
    gap = (du_taken - du_filter).astype(cov.dtype)
    return z + (regress @ gap).astype(z.dtype)
