"""The data of a tracking environment: :class:`EnvParams`, validated and normalised.

Everything a traced step of :mod:`jaxcal.envs.tracking` reads lives here, so that a
new data set, surrogate or reference state track is new input to the compiled
environment, not a recompilation. Built host-side by :func:`make_env_params`, which
checks every field and names the offending one. The normalisation is given, never
computed here: a run's is its problem's (:class:`~jaxcal.problem.Problem` ``norm``).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxcal.problem import Normalisation
from jaxcal.typedefs import Array, PyTree


@struct.dataclass
class EnvParams:
    """Data to track and everything else a traced step reads.

    Attributes:
        w: [U, T, W] operating conditions (physical units), padded after ``lengths``.
        x: [U, T, S] observed outputs (physical units), padded after ``lengths``.
        lengths: [U] int32 valid rows per unit (rows t < lengths[u] are data).
        w_mean, w_std: [W] normalisation of w (training statistics: the problem's
            ``norm`` in the data's dtype).
        x_mean, x_std: [S] normalisation of x and x-hat; x_std is also the cost's sigma.
        theta_low, theta_high: [P] action box.
        dyn_params: pytree passed to ``dynamics`` (surrogate weights, engine constants).
        z_ref: [U, T, Z] reference model state after each sample (where an episode
            starting there takes its z from); ``None`` for a static model.
        step_ref: [P] residual RMS at which an incremental step is half its
            largest (:func:`jaxcal.envs.increment.apply_increment`); ``None`` for
            absolute actions.
        x_target: [U, T, S] what the cost compares the prediction with; ``None``:
            the observations ``x``. Simulated units carry their noise-free outputs
            here (:mod:`jaxcal.training.data.simulated`): the cost of a noisy target
            stops rewarding precision at the noise level, the clean one does not.
        x_noise: [S] the problem's measurement noise std (output units), which the
            filter step of ``EnvConfig.gn_filter`` weighs the outputs by; ``None``
            without it.
        theta_target: [U, T, P] the true theta of each row where it is known (a
            simulated unit's), NaN where not (a real unit's); the cost's theta term
            (``EnvConfig.theta_cost``) reads it. ``None``: no theta term.
    """

    w: Array
    x: Array
    lengths: Array
    w_mean: Array
    w_std: Array
    x_mean: Array
    x_std: Array
    theta_low: Array
    theta_high: Array
    dyn_params: PyTree
    z_ref: Array | None = None
    step_ref: Array | None = None
    x_target: Array | None = None
    x_noise: Array | None = None
    theta_target: Array | None = None


def make_env_params(
    w: Array,
    x: Array,
    lengths: Array,
    theta_low: Array,
    theta_high: Array,
    dyn_params: PyTree,
    *,
    stats: Normalisation,
    z_ref: Array | None = None,
    step_ref: Array | None = None,
    x_target: Array | None = None,
    theta_target: Array | None = None,
) -> EnvParams:
    """Validates the data and assembles :class:`EnvParams` (host-side).

    The arguments are the fields of :class:`EnvParams`, checked: lengths in [2, T],
    ``theta_low < theta_high``, ``w``, ``x``, ``z_ref`` and ``x_target`` finite on
    valid rows, ``step_ref`` positive. ``stats`` is the normalisation (a run's: its
    problem's ``norm``, the training units' statistics, for test and held-out units
    too), cast to the data's dtype.

    Raises:
        ValueError: naming the offending field and the expected form.
    """
    w_np, x_np = np.asarray(w), np.asarray(x)
    lengths_np = np.asarray(lengths)
    low, high = (
        np.atleast_1d(np.asarray(theta_low)),
        np.atleast_1d(np.asarray(theta_high)),
    )
    valid = _check_padded_data(w_np, x_np, lengths_np)
    if low.shape != high.shape or low.ndim != 1 or not np.all(low < high):
        raise ValueError(
            f"theta_low and theta_high must be [P] arrays with theta_low < theta_high, "
            f"got {low} and {high}"
        )
    _check_stats(stats, w_np.shape[-1], x_np.shape[-1])
    z_ref_np = None if z_ref is None else _checked_z_ref(z_ref, x_np, valid)
    if step_ref is not None:
        step_ref = _checked_step_ref(step_ref, low, x_np.dtype)
    if x_target is not None:
        x_target = _checked_x_target(x_target, x_np, valid)
    return EnvParams(
        w=jnp.asarray(w_np),
        x=jnp.asarray(x_np),
        lengths=jnp.asarray(lengths_np, jnp.int32),
        w_mean=jnp.asarray(stats.w_mean, w_np.dtype),
        w_std=jnp.asarray(stats.w_std, w_np.dtype),
        x_mean=jnp.asarray(stats.x_mean, x_np.dtype),
        x_std=jnp.asarray(stats.x_std, x_np.dtype),
        theta_low=jnp.asarray(low),
        theta_high=jnp.asarray(high),
        dyn_params=dyn_params,
        z_ref=None if z_ref_np is None else jnp.asarray(z_ref_np),
        step_ref=step_ref,
        x_target=x_target,
        theta_target=_checked_theta_target(theta_target, x_np, low),
    )


def _checked_theta_target(theta_target, x_np: np.ndarray, low: np.ndarray):
    """``theta_target`` in the data's dtype, shaped ``[U, T, P]`` (NaN: unknown)."""
    if theta_target is None:
        return None
    theta_target = np.asarray(theta_target, x_np.dtype)
    if theta_target.shape != (*x_np.shape[:2], low.shape[0]):
        raise ValueError(
            f"theta_target must be shaped [U, T, P] {(*x_np.shape[:2], low.shape[0])},"
            f" got {theta_target.shape}"
        )
    return jnp.asarray(theta_target)


def _check_padded_data(w_np, x_np, lengths_np) -> np.ndarray:
    """Checks the padded [U, T, .] data and the unit lengths.

    Returns:
        [U, T] bool, True on the valid rows (t < lengths[u]).
    """
    if w_np.ndim != 3 or x_np.ndim != 3 or w_np.shape[:2] != x_np.shape[:2]:
        raise ValueError(
            "w and x must be [U, T, W] and [U, T, S] with equal U, T; got "
            f"{w_np.shape} and {x_np.shape}"
        )
    num_units, num_steps = x_np.shape[:2]
    if lengths_np.shape != (num_units,) or not np.issubdtype(
        lengths_np.dtype, np.integer
    ):
        raise ValueError(f"lengths must be an int array of shape ({num_units},)")
    if lengths_np.min() < 2 or lengths_np.max() > num_steps:
        raise ValueError(f"lengths must lie in [2, T={num_steps}], got {lengths_np}")
    valid = np.arange(num_steps)[None, :] < lengths_np[:, None]
    if not (np.isfinite(w_np[valid]).all() and np.isfinite(x_np[valid]).all()):
        raise ValueError("w and x must be finite on valid rows (t < lengths[u])")
    return valid


def _check_stats(stats: Normalisation, w_dim: int, x_dim: int) -> None:
    """The normalisation's stds must be positive and sized like w and x."""
    for name, value, dim in (
        ("w_std", stats.w_std, w_dim),
        ("x_std", stats.x_std, x_dim),
    ):
        value = np.asarray(value)
        if value.shape != (dim,) or not np.all(value > 0):
            raise ValueError(f"stats.{name} must be a positive [{dim}] array")


def _checked_z_ref(z_ref, x_np: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``z_ref`` in the data's dtype, checked: [U, T, Z], finite on valid rows."""
    z_ref_np = np.asarray(z_ref, x_np.dtype)
    num_units, num_steps = x_np.shape[:2]
    if z_ref_np.ndim != 3 or z_ref_np.shape[:2] != (num_units, num_steps):
        raise ValueError(
            f"z_ref must be [U, T, Z] with [U, T] = ({num_units}, {num_steps}), "
            f"got {z_ref_np.shape}"
        )
    if not np.isfinite(z_ref_np[valid]).all():
        raise ValueError("z_ref must be finite on valid rows (t < lengths[u])")
    return z_ref_np


def _checked_step_ref(step_ref, low: np.ndarray, dtype) -> Array:
    """``step_ref`` as a positive [P] array in the data's dtype."""
    step_ref = np.asarray(step_ref, dtype)
    if step_ref.shape != low.shape or not np.all(step_ref > 0):
        raise ValueError(
            f"step_ref must be a positive [{low.shape[0]}] array, got {step_ref}"
        )
    return jnp.asarray(step_ref)


def _checked_x_target(x_target, x_np: np.ndarray, valid: np.ndarray) -> Array:
    """``x_target`` in the data's dtype, shaped like x and finite on valid rows."""
    x_target = np.asarray(x_target, x_np.dtype)
    if x_target.shape != x_np.shape or not np.isfinite(x_target[valid]).all():
        raise ValueError(
            f"x_target must be finite and shaped like x {x_np.shape}, got "
            f"{x_target.shape}"
        )
    return jnp.asarray(x_target)
