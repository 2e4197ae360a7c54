"""The units the policy trains on, as the tracking environment's parameters.

:func:`make_training_env` takes the run's training fleet (the data's training units,
their simulated copies or both: :meth:`jaxcal.training.data.simulated.Simulations.
training_fleet`) and makes the :class:`~jaxcal.envs.tracking.EnvParams` the policy
learns on: the problem's normalisation (the run's one, computed in the run's dtype
over the real training units when its data were read:
:func:`jaxcal.training.data.calibration.training_norm`) cast to the run's dtype, exact;
for a model with memory the label-free reference states along each unit; for
incremental actions the step gate (:func:`jaxcal.envs.increment.increment_step_ref`).
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from jaxcal.data.padded import Padded
from jaxcal.envs.increment import increment_step_ref
from jaxcal.envs.memory import as_stateful, reference_states
from jaxcal.envs.tracking import EnvParams, make_env_params
from jaxcal.problem import Problem
from jaxcal.training.components import make_dynamics, uses_filter, uses_gauss_newton
from jaxcal.training.config import TrainConfig
from jaxcal.training.data.calibration import CalibrationData
from jaxcal.training.data.simulated import Simulations


def make_training_env(
    cfg: TrainConfig,
    data: CalibrationData,
    sims: Simulations,
    dyn_params,
    dtype,
    log: Callable[[str], None],
) -> EnvParams:
    """The :class:`EnvParams` of the run's training fleet (normalised with the
    problem's normalisation, the real training units' statistics, simulated units
    too; their noise-free outputs the cost's target when there are some); logs the
    step gate of incremental actions."""
    incremental = cfg.env.action == "increment"
    outputs, params = len(data.problem.output_names), len(data.problem.theta_names)
    filtered = uses_filter(cfg.env)
    fleet, target = sims.training_fleet()
    theta_target = sims.training_theta() if cfg.env.theta_cost else None
    if cfg.env.theta_cost and theta_target is None:
        raise ValueError(
            "env.theta_cost needs simulated training units, whose theta is known "
            "(simulate.train=simulated or both), got simulate.train="
            f"{cfg.simulate.train}"
        )
    train_params = training_env_params(
        fleet, data.problem, dyn_params, dtype, cfg.dynamics,
        cfg.env.max_increment if incremental else None,
        x_target=target, theta_target=theta_target,
        # the filter's R: the noise the simulated units carry (given, else
        # estimated), so that its step is the extended Kalman filter's
        x_noise=sims.problem().noise_std if filtered else None,
    )  # fmt: skip
    if incremental:
        log(
            "incremental actions: step gate n_ref "
            f"{np.asarray(train_params.step_ref).tolist()} (residual RMS), largest "
            f"step {cfg.env.max_increment:g} of the box width"
        )
        steps = []
        if uses_gauss_newton(cfg.env, outputs, params):
            steps.append("the residual's Gauss-Newton step")
        if filtered:
            steps.append(
                "an extended Kalman filter's step (random walk env.filter_q="
                f"{cfg.env.filter_q:g}, noise the simulated units' "
                f"{sims.problem().noise_source}), a share env.filter_gain="
                f"{cfg.env.filter_gain:g} of which is its untrained action"
            )
        if steps:
            log(
                f"the policy observes {' and '.join(steps)} (env.gauss_newton="
                f"{cfg.env.gauss_newton}: {outputs} outputs, {params} parameters)"
            )
    return train_params


def training_env_params(
    units: Padded,
    problem: Problem,
    dyn_params,
    dtype,
    dynamics_kind: str,
    max_increment: float | None = None,
    x_target: np.ndarray | None = None,
    x_noise: np.ndarray | None = None,
    theta_target: np.ndarray | None = None,
) -> EnvParams:
    """The :class:`EnvParams` of ``units`` for ``dynamics_kind`` with ``dyn_params``
    (``max_increment``: incremental actions' largest step, ``None``: absolute
    actions; ``x_target [U, T, S]``: the cost's target, ``None``: ``units.x``;
    ``x_noise [S]``: the filter step's measurement noise, ``None``: the
    problem's; ``theta_target [U, T, P]``: the true theta where known, for the
    cost's theta term), normalised with ``problem.norm`` cast to ``dtype``: the run's
    normalisation, computed in ``dtype`` when the problem was made, so the cast is
    exact and the environment, the deployed policy and ``data.json`` share it bit
    for bit."""
    w, x = units.w.astype(dtype), units.x.astype(dtype)
    z_ref = None  # a static model: Z = 0
    dyn = as_stateful(make_dynamics(dynamics_kind, problem))
    if problem.model.is_stateful:
        # The label-free reference: the model along each unit at the prior theta
        # (the joint UKF's filtered states would be closer).
        z_ref = reference_states(
            dyn, dyn_params, w, x, units.lengths, problem.theta_prior
        )
    params = make_env_params(
        w,
        x,
        units.lengths,
        problem.theta_low.astype(dtype),
        problem.theta_high.astype(dtype),
        dyn_params,
        stats=problem.norm,
        z_ref=z_ref,
        x_target=None if x_target is None else x_target.astype(dtype),
        theta_target=None if theta_target is None else theta_target.astype(dtype),
    )
    if max_increment is None:
        return params
    return params.replace(
        step_ref=jnp.asarray(
            increment_step_ref(dyn, params, problem.theta_prior, max_increment), dtype
        ),
        # the filter step's R (gn_filter): make_training_env passes the simulated
        # units' noise (given or estimated); the provisional 1 % of each output's
        # spread mis-weighs the outputs (results/policy_any_model)
        x_noise=jnp.asarray(problem.noise_std if x_noise is None else x_noise, dtype),
    )
