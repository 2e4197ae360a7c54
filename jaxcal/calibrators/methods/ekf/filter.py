"""Extended Kalman filter over the calibrated parameters: the UKF's model, linearised.

The state-space model is the UKF's (:mod:`jaxcal.calibrators.ukf`)::

    theta_t = theta_{t-1} + xi_t,        xi ~ N(0, Q),  Q = q^2 I
    x_t     = F(w_t, theta_t) + eps_t,   eps ~ N(0, R), R = r^2 I  (compared outputs)

with the same units (outputs compared as ``(x - centre) / noise_std``, parameters as
``theta / theta_scale``), the same augmented state ``a = [z / state_scale, theta /
theta_scale]`` for a model with memory ``(z_t, x_t) = step(z_{t-1}, w_t, theta_t)``
(the joint state-and-parameter EKF, e.g. Ljung 1979, "Asymptotic behavior of the
extended Kalman filter as a parameter estimator for linear systems", IEEE TAC 24(1))
and ``Z = 0`` for a static model (:func:`make_ekf`). It is filtered with the
additive-noise EKF of Särkkä (2013), "Bayesian Filtering and Smoothing", alg. 5.4::

    P'  = P + Q_theta                        (identity prediction of theta: exact)
    [z_t, y_t] ~ g(m) + G (a - m),           g = propagate, G = [F_a; H_a] at m
    P_t = F_a P' F_a^T + Q_state,   C = F_a P' H_a^T,   S = H_a P' H_a^T + R
    K = C S^-1,   m_t = [g_z(m), m_theta] + K (y - g_y(m)),   P_t -= K S K^T

(the parameter block of ``P_t`` kept at ``P'_thth``, its exact value, as the UKF does).

Why forward mode: with ``L = chol(P' + jitter I)``, ``F_a P' F_a^T = (F_a L)(F_a
L)^T`` and alike, and ``G L`` is ``n = Z + P`` Jacobian-vector products along the
columns of ``L``. They are taken as ``jax.jvp`` vmapped over the columns with the
primal unbatched: one pass carries the model's evaluation once and its ``n``
tangents together, against the UKF's ``2n + 1`` sigma-point evaluations
(``jax.linearize`` splits a loop in the model into a primal pass that stores its
residuals and a slower tangent pass, and re-runs a ``while_loop`` solver whole in
the tangent pass). Forward mode goes through ``while_loop`` solvers, which reverse mode
does not, and ``n`` is small where the number of outputs need not be. The tangent rows
``G L`` are the "linearised deviations" of unit weight that the UKF's update
(:func:`~jaxcal.calibrators.ukf_steps.update`) takes, so missing outputs, the
log-likelihood and the symmetrised covariance are the UKF's code; on a linear model both
filters are the exact Kalman filter and agree to round-off.

The prior of a model with memory linearises ``z0 = init(w0, theta)`` at the prior
mean (:func:`linear_joint_prior`). Box projection of the mean and clipping of the
evaluated parameters are the UKF's. Float64 is recommended, as for the UKF.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxcal.calibrators.gaussian_filter import (
    Moments,
    make_gaussian_filter,
    static_transition,
)
from jaxcal.calibrators.interface import Calibrator, MeasureFn, Measurement
from jaxcal.calibrators.ukf_steps import UKFState, _Prediction
from jaxcal.problem import Transition
from jaxcal.typedefs import Array


@dataclasses.dataclass(frozen=True)
class EKFConfig:
    """Static EKF settings (hashable, closed over by :func:`make_ekf`)."""

    q: float = 0.01  # random-walk std per step, scaled-theta units
    r: float = 0.01  # noise std in units of Measurement.noise_std
    prior_std: float = 1.0  # std of theta_0 around theta0, scaled-theta units
    jitter: float = 1e-10  # added to the covariance diagonal before Cholesky
    posterior_xhat: bool = True  # xhat = F(w, theta_post): one extra evaluation
    return_cov: bool = False  # also report aux["theta_cov"] [P, P]

    def __post_init__(self):
        for name in ("q", "r", "prior_std"):
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"EKFConfig.{name} must be > 0, got {getattr(self, name)}"
                )
        if not self.jitter >= 0:
            raise ValueError(f"EKFConfig.jitter must be >= 0, got {self.jitter}")


def make_ekf(
    measure_fn: MeasureFn, cfg: EKFConfig, measurement: Measurement, **options
) -> Calibrator:
    """The EKF of a static model ``F(w [Wd], theta [P]) -> x [S]``: arguments
    (``options``: ``theta0``, ``theta_scale``, ``theta_box``), state
    (:class:`~jaxcal.calibrators.ukf_steps.UKFState`) and outputs as
    :func:`~jaxcal.calibrators.ukf.make_ukf`. ``F`` must be jittable and
    differentiable in forward mode (``jax.jvp``)."""
    return make_joint_ekf(
        static_transition(measure_fn), cfg, measurement, clip_points=False, **options
    )


def linearised(cfg: EKFConfig) -> Moments:
    """The EKF's moments: the prediction and the prior of a model with memory
    linearised at the mean (:func:`linearised_predict`, :func:`linear_joint_prior`);
    the tangent rows have unit weight."""
    return Moments(
        predict=lambda state, propagate, noise, weights, num_states: linearised_predict(
            state, propagate, noise, cfg.jitter, num_states
        ),
        prior=lambda at_rest, u0, cov_u, s_std, s_scale: linear_joint_prior(
            at_rest, u0, cov_u, cfg.jitter, s_std, s_scale
        ),
        weights=lambda n, dtype: (None, jnp.ones((n,), dtype), None),
    )


def make_joint_ekf(
    transition: Transition, cfg: EKFConfig, measurement: Measurement, **options
) -> Calibrator:
    """The joint (augmented) state-and-parameter EKF of a model with memory.

    Arguments (``options``: ``theta0``, ``theta_scale``, ``state_std``, ``state_q``,
    ``state_scale``, ``theta_box``, ``clip_points``) and outputs as
    :func:`~jaxcal.calibrators.ukf.make_joint_ukf` (the same skeleton,
    :func:`~jaxcal.calibrators.gaussian_filter.make_gaussian_filter`);
    ``clip_points`` clips the parameters the model is evaluated (and linearised) at
    into ``theta_box``. Each step evaluates ``transition.step`` once carrying ``Z +
    P`` forward-mode tangents, plus once more with ``cfg.posterior_xhat``.
    """
    return make_gaussian_filter(
        linearised(cfg), transition, cfg, measurement, **options
    )


def linearised_predict(
    state: UKFState, propagate, noise, jitter: float, num_states: int
) -> _Prediction:
    """The EKF prediction in the UKF's form: ``propagate(a) -> (z_t / state_scale,
    normalised x_t)`` linearised at the mean of ``P' = P + Q_theta``, its tangents
    along the columns of ``L = chol(P' + jitter I)`` as the deviations ``da [n, n]``
    (state rows ``F_z L``, parameter rows ``L``'s) and ``dy [n, S]`` (``H L``), so
    that ``da^T da = F P' F^T``, ``da^T dy = F P' H^T`` and ``dy^T dy = H P' H^T``."""
    q_theta, q_state = noise
    mean_prior = state.mean
    cov_prior = state.cov + q_theta
    n = mean_prior.shape[0]
    chol = jnp.linalg.cholesky(cov_prior + jitter * jnp.eye(n, dtype=cov_prior.dtype))

    # jvp vmapped over L's columns: the primal is unbatched, so the model is
    # evaluated once and carries the n tangents in the same pass (module docstring)
    def along(col):
        return jax.jvp(propagate, (mean_prior,), (col,))

    (z_mean, y_mean), (dz, dy) = jax.vmap(along, out_axes=(None, 0))(chol.T)
    da = jnp.concatenate([dz, chol.T[:, num_states:]], axis=1)
    mean_pred = jnp.concatenate([z_mean, mean_prior[num_states:]])
    if num_states:
        cov_pred = da.T @ da + q_state
        # theta's prediction is the identity: keep its block exact (no jitter)
        cov_pred = cov_pred.at[num_states:, num_states:].set(
            cov_prior[num_states:, num_states:]
        )
    else:
        cov_pred = cov_prior
    return _Prediction(mean_pred, cov_pred, da, y_mean, dy)


def linear_joint_prior(
    at_rest, u0: Array, cov_u: Array, jitter: float, s_std: Array, s_scale: Array
) -> UKFState:
    """The prior of ``[z0 / state_scale, u0]`` with ``z0 = at_rest(u) = init(w0,
    theta)`` linearised at ``u0``: mean ``at_rest(u0)``, cross-covariance ``J
    cov_u``, state covariance ``J cov_u J^T + diag(state_std^2)`` (the linearised
    analogue of :func:`~jaxcal.calibrators.ukf_steps.joint_prior`)."""
    z_of_u = lambda u: jnp.asarray(at_rest(u), u0.dtype) / s_scale  # noqa: E731
    z_mean = z_of_u(u0)
    jac = jax.jacfwd(z_of_u)(u0)  # [Z, P]: P tangents, once per record
    # the jitter as the UKF's sigma points carry it: on a linear init, the same prior
    cov_zu = jac @ (cov_u + jitter * jnp.eye(u0.shape[0], dtype=cov_u.dtype))
    cov_zz = cov_zu @ jac.T + jnp.diag((s_std / s_scale) ** 2)
    cov = jnp.block([[cov_zz, cov_zu], [cov_zu.T, cov_u]])
    return UKFState(mean=jnp.concatenate([z_mean, u0]), cov=cov)
