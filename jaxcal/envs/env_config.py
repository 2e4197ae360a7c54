"""Static configuration of the tracking environment and the checks of its data.

:class:`EnvConfig` holds the sizes and choices that shape the traced program
(:mod:`jaxcal.envs.tracking`); :func:`check_env_params` checks an
:class:`~jaxcal.envs.env_data.EnvParams` against it before any tracing.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from jaxcal.envs.env_data import EnvParams
from jaxcal.envs.increment import FILTER_PRIOR_STD, FILTER_Q


def check_action_options(
    action: str, max_increment: float, cost: str, cost_floor: float
) -> None:
    """Validates the action and cost options (:class:`EnvConfig`, and the training
    config's ``env.*`` fields before any work).

    Raises:
        ValueError: naming the ``env.`` field and its allowed values.
    """
    if action not in ("absolute", "increment"):
        raise ValueError(
            f"env.action must be 'absolute' or 'increment', got {action!r}"
        )
    if not 0.0 < max_increment <= 1.0:
        raise ValueError(f"env.max_increment must be in (0, 1], got {max_increment}")
    if cost not in ("squared", "log") or not cost_floor > 0:
        raise ValueError(
            "env.cost must be 'squared' or 'log' and env.cost_floor > 0, got "
            f"{cost!r}, {cost_floor}"
        )


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Static configuration of the tracking environment.

    Attributes:
        sensor_dim: S, number of observed outputs x.
        condition_dim: W, number of operating conditions w.
        param_dim: P, number of calibrated parameters theta.
        episode_length: steps per training episode (window length).
        differentiable: if True, gradients flow through the transition.
        action: ``"absolute"``: the action sets theta (the paper's); ``"increment"``:
            the action changes theta, gated by the residual
            (:mod:`jaxcal.envs.increment`).
        max_increment: the largest change of theta per step as a share of the box
            width (``action="increment"`` only).
        cost: ``"squared"``: c = mean_S ((x - x-hat) / sigma)^2 (the paper's);
            ``"log"``: log(1 + c / floor^2), which weighs a halving of the error the
            same at every scale (a feedback policy must keep contracting the error
            where the outputs barely see theta, at idle, not only where they do).
        cost_floor: the residual RMS below which the log cost is flat.
        gauss_newton: incremental actions only: the observation also holds the
            Gauss-Newton step of the residual through the model's Jacobian and the
            stream's age (:func:`~jaxcal.envs.increment.gauss_newton_features`), so
            the network learns a gain schedule rather than the model's inverse.
        gn_filter: it also holds an extended Kalman filter's step on theta
            (:func:`~jaxcal.envs.increment.filter_feature`), its random walk per
            sample ``filter_q`` and its prior std ``filter_prior_std`` in half-widths
            of the box; ``filter_whole``: a unit gain on it is the filter's whole
            step at any residual (the gate divided out), on a model with memory the
            joint filter of state and theta (:mod:`~jaxcal.envs.joint_filter`);
            ``False``: the gate's small-residual slope and theta alone.
        theta_cost: weight of ``mean_P(((theta - theta*) / h)^2)`` (``h`` the box's
            half-widths) added to the tracking cost before the log where the true
            theta is known (``EnvParams.theta_target``); 0: tracking alone (the
            paper's).
        filter_adapt: with ``gn_filter`` on a static model, the filter weighs each
            output by the noise its innovations show, averaged over this many
            samples (:func:`~jaxcal.envs.increment.adapted_noise_scale`); 0: the
            declared noise.
    """

    sensor_dim: int
    condition_dim: int
    param_dim: int
    episode_length: int = 100
    differentiable: bool = False
    action: str = "absolute"
    max_increment: float = 0.5
    cost: str = "squared"
    cost_floor: float = 1e-4
    gauss_newton: bool = False
    gn_filter: bool = False
    filter_q: float = FILTER_Q
    filter_whole: bool = False
    filter_prior_std: float = FILTER_PRIOR_STD
    theta_cost: float = 0.0
    filter_adapt: int = 0

    def __post_init__(self) -> None:
        for name in ("sensor_dim", "condition_dim", "param_dim", "episode_length"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(
                    f"EnvConfig.{name} must be a positive int, got {value!r}"
                )
        check_action_options(
            self.action, self.max_increment, self.cost, self.cost_floor
        )
        if self.uses_jacobian and not self.incremental:
            raise ValueError(
                "env.gauss_newton needs env.action='increment' (it is the step of "
                "an incremental action's residual)"
            )

    @property
    def uses_jacobian(self) -> bool:
        """True when the observation holds a step through the model's Jacobian."""
        return self.gauss_newton or self.gn_filter

    @property
    def incremental(self) -> bool:
        """True when the action changes theta rather than setting it."""
        return self.action == "increment"

    @property
    def observation_size(self) -> int:
        """Size of s_t: 2 S + W ([x-hat_t, x_{t+1}, w_{t+1}]), or S + 1 + W + P for
        incremental actions ([r / |r|, lg |r|, w_{t+1}, theta_t]), P more with
        ``gauss_newton``, P more with ``gn_filter`` (and the age with either)."""
        if self.incremental:
            extra = self.param_dim * (int(self.gauss_newton) + int(self.gn_filter))
            extra += int(self.uses_jacobian)
            return self.sensor_dim + 1 + self.condition_dim + self.param_dim + extra
        return 2 * self.sensor_dim + self.condition_dim

    @property
    def min_unit_length(self) -> int:
        """Shortest unit a training window fits in: episode_length + 2 samples."""
        return self.episode_length + 2


def check_dims(params: EnvParams, cfg: EnvConfig) -> None:
    """Checks the last dimensions of x, w and theta_low against ``cfg``.

    Raises:
        ValueError: naming the field, its dimension and the expected one.
    """
    # Shapes are static under tracing, so inside jit this runs once per compilation.
    for name, want in (
        ("x", cfg.sensor_dim),
        ("w", cfg.condition_dim),
        ("theta_low", cfg.param_dim),
    ):
        got = getattr(params, name).shape[-1]
        if want != got:
            raise ValueError(
                f"EnvParams.{name} has last dimension {got}, EnvConfig expects {want}"
            )


def check_env_params(params: EnvParams, cfg: EnvConfig) -> None:
    """Checks that ``params`` fit ``cfg``: dimensions, and window length when concrete.

    Raises:
        ValueError: if a dimension differs or no unit is long enough for one window.
    """
    check_dims(params, cfg)
    if isinstance(params.lengths, jax.core.Tracer):
        return  # abstract evaluation (jit, eval_shape): only shapes can be checked
    longest = int(np.max(np.asarray(params.lengths)))
    if longest < cfg.min_unit_length:
        raise ValueError(
            f"no unit is long enough for episode_length={cfg.episode_length}: the "
            f"longest has {longest} rows, a window needs {cfg.min_unit_length}"
        )
