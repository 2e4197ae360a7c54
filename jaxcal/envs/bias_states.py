"""Output-bias states of the policy's filter: a sensor's slow error beside theta.

The filter the policy starts from explains every persistent residual by theta: a
sensor that reads 3 noise stds high moves theta until the model reads high too, and
the UKF does the same. A classic remedy is to estimate the bias with the parameters
(Friedland (1969), "Treatment of bias in recursive filtering", IEEE TAC 14(4)):
each output ``k`` gets a state ``b_k`` in its noise's units, a random walk of
variance ``v_k`` per sample, and the model's prediction becomes ``x-hat + sigma b``.
A bias is then told from theta wherever theta cannot make it: outputs to spare, or
conditions that move and make theta's effect move with them while the bias stays.

The price is the other way round: where ``v`` is large, a change of theta is read
in part as a bias, and clean data lose. ``v`` is therefore not set by hand but
fitted, per output, by the tuning through the filter (``tune.bias``,
:mod:`jaxcal.training.stages.tune`): the untrained policy has no bias states (the
filter as before, bit for bit), and the tuning starts them at a walk that changes
nothing (:data:`START_WALK`) and keeps what the simulated units with and without
undeclared effects agree on.

The filter with these states is the joint filter of a model with memory
(:mod:`jaxcal.envs.joint_filter`) with the biases appended to the model's state,
``[z, b, u]`` (theta's block stays last, where the band and the state's regression
on theta read it). On a static model the state is ``b`` alone.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.typedefs import Array

# the walks the tuning scores before its gradient steps, one per decade: the log
# walk's gradient at START_WALK is too faint to climb decades in a few hundred steps
BIAS_WALKS = (1e-4, 1e-3, 1e-2)
# the tuning's first bias walk per sample, (noise stds)^2: a bias of 0.03 noise
# stds after 1,000 samples, which changes no scored theta of the studies' units
START_WALK = 1e-6


def biased_jacobians(joint, x_noise: Array, param_dim: int):
    """``(A', H')`` of the filter with bias states: the model's step Jacobians
    ``(A [Z, Z + P], H [S, Z + P])`` in ``(z, u)`` (:func:`static_joint` for a
    static model) extended to ``(z, b, u)``: the bias keeps its value (``I``) and
    adds ``sigma`` (``x_noise``) to the prediction."""
    sigma = x_noise
    num_out = sigma.shape[0]
    a, h = joint
    num_states = a.shape[0]
    a_z, a_u = a[:, :num_states], a[:, num_states:]
    h_z, h_u = h[:, :num_states], h[:, num_states:]
    zeros = jnp.zeros((num_states, num_out), a.dtype)
    eye = jnp.eye(num_out, dtype=a.dtype)
    a_b = jnp.concatenate([jnp.zeros((num_out, num_states), a.dtype), eye], axis=1)
    a_new = jnp.concatenate(
        [
            jnp.concatenate([a_z, zeros, a_u], axis=1),
            jnp.concatenate([a_b, jnp.zeros((num_out, param_dim), a.dtype)], axis=1),
        ],
        axis=0,
    )
    h_new = jnp.concatenate([h_z, jnp.diag(sigma).astype(h.dtype), h_u], axis=1)
    return a_new, h_new


def static_joint(jac: Array, half: Array):
    """``(A [0, P], H [S, P])`` of a static model's step in half-box units ``u``
    (the model has no state: the joint form of its Jacobian ``jac`` ``[S, P]``)."""
    h = jac * half[None, :].astype(jac.dtype)
    return jnp.zeros((0, jac.shape[1]), jac.dtype), h


def with_bias_block(cov: Array, num_states: int, num_out: int) -> Array:
    """``cov`` ``[Z + P, Z + P]`` with the biases' block inserted after the state,
    ``[Z + S + P, Z + S + P]``: the biases start at zero and known."""
    n = cov.shape[0]
    out = jnp.zeros((n + num_out, n + num_out), cov.dtype)
    keep = jnp.concatenate(
        [jnp.arange(num_states), num_states + num_out + jnp.arange(n - num_states)]
    )
    return out.at[keep[:, None], keep[None, :]].set(cov)


def bias_walk(num_states: int, bias_var: Array, dtype) -> Array:
    """``[Z + S]`` the random walk of the filter's ``(z, b)`` block per sample: none
    on the model's state, ``bias_var`` on the biases."""
    return jnp.concatenate([jnp.zeros(num_states, dtype), bias_var.astype(dtype)])


def bias_rate(bias_var: Array, noise_scale: Array | None) -> Array:
    """``[S]`` the biases' walk this sample: ``bias_var`` on a model whose filter
    does not adapt its noise; where it does (a static model with outputs to spare,
    ``filter_adapt``), only on the outputs whose innovations show more than their
    noise beyond what theta explains, ``bias_var (scale - 1)+``. A bias on every
    output at once is never told from theta on a static model (as many unknowns
    again as outputs); this keeps the bias states to the outputs that need them."""
    if noise_scale is None:
        return bias_var
    return bias_var * jnp.maximum(noise_scale.astype(bias_var.dtype) - 1.0, 0.0)


def debiased(resid: Array, bias: Array, x_noise: Array, x_std: Array) -> Array:
    """The normalised innovation ``(x - x-hat - sigma b) / x_std`` of the residual
    ``resid`` ``[S]`` (``(x - x-hat) / x_std``) given the biases ``b``."""
    return resid - (bias * x_noise / x_std).astype(resid.dtype)
