"""Fitting the surrogate D on fleet transitions, and measuring how well it imitates F.

Training pairs are (w_{t+1}, x_t, θ_{t+1}) → x_{t+1} from consecutive samples of each
unit of a padded data set (:func:`make_transitions`); a pair is kept only when both of
its samples are valid, so no pair straddles the padding at the end of a short unit.
:func:`fit_surrogate` standardises inputs and targets and runs the shared minibatch Adam
trainer. :func:`surrogate_errors` reports, per sensor, the one-step error (D fed the
measured x_t) and the free-running error (D fed back its own x̂_t from x̂_0 = x_0, the
way the tracking environment uses it), as RMSE in sensor units and divided by the
training std of that sensor.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.nets.mlp import fit_regressor
from jaxcal.surrogate.model import (
    SurrogateConfig,
    SurrogateParams,
    make_surrogate_network,
    surrogate_apply,
    surrogate_rollout,
)
from jaxcal.typedefs import Array, PRNGKey


class Transitions(NamedTuple):
    """Flat training pairs for D; M valid pairs taken from a ``[U, T]`` fleet."""

    w_next: np.ndarray  # [M, W] operating condition at t + 1
    x: np.ndarray  # [M, S] measured output at t
    theta_next: np.ndarray  # [M, P] calibration parameters at t + 1
    x_next: np.ndarray  # [M, S] measured output at t + 1 (the target)


def _check_fleet(w, x, theta, mask) -> tuple[np.ndarray, ...]:
    w, x, theta = (np.asarray(v) for v in (w, x, theta))
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be [U, T], got shape {mask.shape}")
    for name, v in (("w", w), ("x", x), ("theta", theta)):
        if v.ndim != 3 or v.shape[:2] != mask.shape:
            raise ValueError(
                f"{name} must be [U, T, ·] with [U, T] = {mask.shape}, got {v.shape}"
            )
    return w, x, theta, mask


def pair_mask(mask: Array) -> Array:
    """``[U, T-1]``: True where samples t and t + 1 of a unit are both valid."""
    return mask[:, :-1] & mask[:, 1:]


def make_transitions(w: Array, x: Array, theta: Array, mask: Array) -> Transitions:
    """Build D's training pairs from a padded fleet (host-side: M depends on the mask).

    Args:
        w: ``[U, T, W]`` operating conditions.
        x: ``[U, T, S]`` sensor readings (from F or measured).
        theta: ``[U, T, P]`` calibration parameters.
        mask: ``[U, T]`` validity of each sample.

    Returns:
        :class:`Transitions` of the M pairs whose two samples are both valid, in unit
        then time order.

    Raises:
        ValueError: when the shapes disagree or no valid pair exists.
    """
    w, x, theta, mask = _check_fleet(w, x, theta, mask)
    keep = np.flatnonzero(pair_mask(mask).reshape(-1))
    if keep.size == 0:
        raise ValueError("mask leaves no pair of consecutive valid samples")

    def flat(v):
        return v.reshape(-1, v.shape[-1])[keep]

    return Transitions(
        w_next=flat(w[:, 1:]),
        x=flat(x[:, :-1]),
        theta_next=flat(theta[:, 1:]),
        x_next=flat(x[:, 1:]),
    )


def fit_surrogate(
    key: PRNGKey,
    transitions: Transitions,
    cfg: SurrogateConfig,
    *,
    log_fn: Callable[[int, dict[str, float]], None] | None = None,
    progress: bool = False,
) -> tuple[SurrogateParams, dict]:
    """Fit D to the transitions by minibatch Adam on the normalised MSE.

    Args:
        key: PRNG key (initialisation, validation split, minibatch order).
        transitions: pairs from :func:`make_transitions`.
        cfg: architecture and optimisation settings.
        log_fn: per-epoch callback ``log_fn(epoch, {"train_loss", "val_loss"})``.
        progress: show a progress bar.

    Returns:
        ``(params, history)`` as in :func:`jaxcal.nets.mlp.fit_regressor`.
    """
    condition_dim = transitions.w_next.shape[-1]
    sensor_dim = transitions.x.shape[-1]
    theta_dim = transitions.theta_next.shape[-1]
    inputs = np.concatenate(
        [transitions.w_next, transitions.x, transitions.theta_next], axis=-1
    )
    net = make_surrogate_network(cfg.hidden_sizes, sensor_dim, cfg.activation)
    regressor, history = fit_regressor(
        key, net, inputs, transitions.x_next, cfg.fit, log_fn=log_fn, progress=progress
    )
    params = SurrogateParams(
        regressor=regressor,
        hidden_sizes=tuple(cfg.hidden_sizes),
        activation=cfg.activation,
        condition_dim=condition_dim,
        sensor_dim=sensor_dim,
        theta_dim=theta_dim,
    )
    return params, history


def _masked_rmse(err: Array, valid: Array) -> Array:
    """Per-sensor RMSE ``[S]`` of ``err [U, T, S]`` over ``valid [U, T]`` entries."""
    sq = jnp.where(valid[..., None], err**2, 0.0)  # where, not *: padding may be NaN
    return jnp.sqrt(jnp.sum(sq, axis=(0, 1)) / jnp.sum(valid))


@jax.jit
def _errors(params, w, x, theta, mask):
    valid = pair_mask(mask)
    one_step = surrogate_apply(params, w[:, 1:], x[:, :-1], theta[:, 1:])
    free_run = jax.vmap(surrogate_rollout, in_axes=(None, 0, 0, 0))(
        params, w, x[:, 0], theta
    )[:, 1:]
    std = params.regressor.target_norm.std
    out = {}
    for name, pred in (("one_step", one_step), ("free_run", free_run)):
        rmse = _masked_rmse(pred - x[:, 1:], valid)
        out[f"{name}_rmse"] = rmse
        out[f"{name}_rmse_norm"] = rmse / std
        out[f"{name}_rmse_norm_mean"] = jnp.mean(rmse / std)
    return out


def surrogate_errors(
    params: SurrogateParams, w: Array, x: Array, theta: Array, mask: Array
) -> dict[str, Array]:
    """One-step and free-running errors of D against the recorded outputs, per sensor.

    One-step: x̂_{t+1} = D(w_{t+1}, x_t, θ_{t+1}) with the measured x_t. Free-running:
    x̂_0 = x_0, then x̂_{t+1} = D(w_{t+1}, x̂_t, θ_{t+1}) along each unit (``lax.scan``,
    vmapped over units), i.e. the drift the tracking environment sees. Both are scored
    on valid pairs only.

    Args:
        params: trained surrogate.
        w: ``[U, T, W]``; x: ``[U, T, S]``; theta: ``[U, T, P]``; mask: ``[U, T]``.

    Returns:
        ``{one_step,free_run}_rmse`` ``[S]`` in sensor units,
        ``{one_step,free_run}_rmse_norm`` ``[S]`` divided by the training std of each
        sensor, ``{one_step,free_run}_rmse_norm_mean`` (scalar mean over sensors) and
        ``num_pairs``.
    """
    w, x, theta, mask = _check_fleet(w, x, theta, mask)
    num_pairs = int(pair_mask(mask).sum())
    if num_pairs == 0:
        raise ValueError("mask leaves no pair of consecutive valid samples")
    out = _errors(params, jnp.asarray(w), jnp.asarray(x), jnp.asarray(theta), mask)
    out["num_pairs"] = num_pairs
    return out
