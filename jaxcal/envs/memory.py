"""The memory of a model in the tracking MDP: :class:`StatefulDynamics`.

A model with hidden states (``Model.from_step``) maps ``(z_t, w_t, theta) -> (z_{t+1},
x_t)`` (:meth:`jaxcal.problem.Problem.transition`). The tracking environment, the
policy calibrator and deployment carry ``z`` beside the model output x-hat, so the
transition of the MDP becomes

    (z', x-hat_{t+1}) = step(dyn_params, z, w_{t+1}, x-hat_t, theta_{t+1}),

where ``z`` is the model state *after* the current sample. A plain (static)
``dynamics(dyn_params, w_next, xhat, theta) -> xhat_next`` is the special case
``Z = 0`` (:func:`as_stateful`): z is ``None``, passed through, and x-hat is exactly
the callable's, so a static run computes the very numbers it did before z existed.
(``None`` rather than a ``[0]`` array: Orbax refuses to checkpoint zero-size arrays;
the environment then keeps its plain state, so a static run's checkpoints keep their
layout and older runs resume.)

Where an episode or a stream starts, z must come from somewhere:

* :attr:`StatefulDynamics.init` gives the state after a stream's first sample, with
  the prior theta (deployment: nothing else is known yet);
* :func:`reference_states` gives the state after every sample of every unit by
  running the same two functions along the unit with the prior theta: the training
  environment's reset reads it (``EnvParams.z_ref``), so an episode starting at
  sample t begins from the state a deployed calibrator would carry there if theta had
  stayed at its prior, and ``reset_at(unit, 0)`` agrees exactly with ``init``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.typedefs import Array, PyTree


class StatefulDynamics(NamedTuple):
    """A transition that carries a hidden model state ``z [Z]`` besides x-hat.

    Attributes:
        step: ``step(dyn_params, z [Z], w_next [W], xhat [S], theta [P]) -> (z_next
            [Z], xhat_next [S])``; ``z`` is the model state after the current sample.
        init: ``init(dyn_params, w0 [W]) -> z [Z]``: the state after a stream's first
            sample, with the prior theta closed over (``None`` when ``Z = 0``).
        num_states: ``Z``.
        init_at: ``init_at(dyn_params, w0, theta [P]) -> z [Z]``: the same state at
            any theta (``init`` is it at the prior), from which a joint filter
            learns how the first state moves with theta
            (:func:`~jaxcal.envs.joint_filter.joint_prior`); ``None``: unknown.
    """

    step: Callable
    init: Callable
    num_states: int
    init_at: Callable | None = None


def as_stateful(dynamics) -> StatefulDynamics:
    """``dynamics`` as a :class:`StatefulDynamics`; a plain callable gets ``Z = 0``
    (z is ``None`` and passes through, x-hat is exactly the callable's).

    Raises:
        ValueError: ``dynamics`` is neither.
    """
    if isinstance(dynamics, StatefulDynamics):
        return dynamics
    if not callable(dynamics):
        raise ValueError(f"dynamics must be callable, got {type(dynamics).__name__}")

    def step(dyn_params, z, w_next, xhat, theta):
        return z, dynamics(dyn_params, w_next, xhat, theta)

    def init(dyn_params, w0):
        del dyn_params, w0
        return None

    return StatefulDynamics(step=step, init=init, num_states=0)


def transition_dynamics(
    transition, theta_prior: np.ndarray, *, x64: bool = False
) -> StatefulDynamics:
    """The physics transition of a model with memory as :class:`StatefulDynamics`.

    Args:
        transition: :class:`~jaxcal.problem.Transition` (``init``, ``step``,
            ``num_states``) on the calibrated parameters and used outputs.
        theta_prior: ``[P]`` the prior theta a stream's first state is built with.
        x64: run the model in float64 (``model.x64``); otherwise in x-hat's dtype.

    Returns:
        :class:`StatefulDynamics`; ``dyn_params`` is ignored (the model's constants
        are closed over).
    """
    prior = np.asarray(theta_prior, np.float64)

    def cast(dtype):
        return jnp.float64 if x64 else dtype

    def step(dyn_params, z, w_next, xhat, theta):
        del dyn_params
        dtype = cast(xhat.dtype)
        z_next, x = transition.step(
            z.astype(dtype), w_next.astype(dtype), theta.astype(dtype)
        )
        return z_next.astype(z.dtype), x.astype(xhat.dtype)

    def init_at(dyn_params, w0, theta):
        # The state *after* the first sample: z_0 = init(w_0), then one step on w_0.
        del dyn_params
        dtype = cast(jnp.result_type(w0))
        w0_, theta = w0.astype(dtype), jnp.asarray(theta, dtype)
        z_next, _ = transition.step(transition.init(w0_, theta), w0_, theta)
        return z_next.astype(jnp.result_type(w0))

    def init(dyn_params, w0):
        return init_at(dyn_params, w0, prior)

    return StatefulDynamics(step, init, transition.num_states, init_at)


def reference_states(
    dynamics: StatefulDynamics,
    dyn_params: PyTree,
    w: Array,
    x: Array,
    lengths: Array,
    theta: Array,
) -> np.ndarray:
    """``[U, T, Z]`` model state after every sample, theta held at ``theta``.

    ``z[u, 0] = init(w[u, 0])``, ``z[u, t] = step(z[u, t-1], w[u, t], theta)`` —
    ``lax.scan`` over time, ``vmap`` over units, jitted once per call; rows at or
    after ``lengths[u]`` (padding) are zero.

    Args:
        dynamics: the run's :class:`StatefulDynamics`.
        dyn_params: its parameters.
        w: ``[U, T, W]`` conditions; x: ``[U, T, S]`` (only its dtype and S are read:
            the physics step ignores x-hat).
        lengths: ``[U]`` valid rows per unit.
        theta: ``[P]`` the held theta (the prior).

    Returns:
        ``[U, T, Z]`` numpy array in x's dtype.

    Raises:
        ValueError: ``dynamics`` carry no state (a static model has no reference).
    """
    if dynamics.num_states == 0:
        raise ValueError("reference_states: the dynamics carry no state (Z = 0)")
    w, x = jnp.asarray(w), jnp.asarray(x)
    theta = jnp.asarray(theta, x.dtype)
    num_steps = x.shape[1]

    def unit(w_u, x_u, length):
        def body(z, inputs):
            w_t, x_t = inputs
            z_next, _ = dynamics.step(dyn_params, z, w_t, x_t, theta)
            return z_next, z_next

        z0 = dynamics.init(dyn_params, w_u[0]).astype(x.dtype)
        _, z_rest = jax.lax.scan(body, z0, (w_u[1:], x_u[1:]))
        z = jnp.concatenate([z0[None], z_rest])
        valid = jnp.arange(num_steps) < length
        return jnp.where(valid[:, None], z, 0.0)

    z = jax.jit(jax.vmap(unit))(w.astype(x.dtype), x, jnp.asarray(lengths))
    return np.asarray(z)


class HintedDynamics(NamedTuple):
    """A static transition with a warm start (a model's ``hinted_fn``).

    Called like the plain transition (``dynamics(dyn_params, w_next, xhat, theta)``,
    what training uses); a deployed stream may instead carry the model's solver hint
    (:meth:`jaxcal.model.Model.evaluate_hinted`) from sample to sample. The hint
    changes x-hat only within the model's solver tolerance; it is not a model
    state (nothing about the model's memory), so the training environment ignores it.

    Attributes:
        plain: ``plain(dyn_params, w_next, xhat, theta) -> xhat_next``.
        step: ``step(dyn_params, hint, w_next, xhat, theta) -> (hint, xhat_next)``.
        init_hint: ``init_hint() -> hint`` before a stream's first sample.
    """

    plain: Callable
    step: Callable
    init_hint: Callable

    def __call__(self, dyn_params, w_next, xhat, theta):
        return self.plain(dyn_params, w_next, xhat, theta)

    def map_output(self, fn: Callable) -> HintedDynamics:
        """The same transition with ``fn(xhat_next) -> xhat_next`` applied to its
        output on both paths (e.g. a perturbation of the model's output)."""

        def plain(dyn_params, w_next, xhat, theta):
            return fn(self.plain(dyn_params, w_next, xhat, theta))

        def step(dyn_params, hint, w_next, xhat, theta):
            hint, out = self.step(dyn_params, hint, w_next, xhat, theta)
            return hint, fn(out)

        return HintedDynamics(plain, step, self.init_hint)
