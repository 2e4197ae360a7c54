"""The E2E network's prediction over whole trajectories at once: the batch
reference the streaming calibrator must reproduce (``test_e2e.py``)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.calibrators.methods.e2e.network import (
    E2EParams,
    _apply,
    e2e_apply,
    e2e_features,
    window_features,
)


def e2e_predict(
    params: E2EParams, w: jnp.ndarray, x: jnp.ndarray, mask: jnp.ndarray | None = None
) -> jnp.ndarray:
    """Parameters of whole trajectories: ``theta [..., T, P]`` from ``w``, ``x``.

    Args:
        params: trained G.
        w: ``[U, T, W]`` (or ``[T, W]``); x: ``[U, T, S]`` (or ``[T, S]``).
        mask: optional ``[U, T]`` validity (see :func:`e2e_features`); outputs at
            invalid samples are meaningless and left to the caller to mask.
    """
    if params.window:
        feats = window_features(jnp.asarray(w), jnp.asarray(x), mask, params.window)
        return _apply(params, feats, jnp.asarray(x))
    features = e2e_features(jnp.asarray(w), jnp.asarray(x), mask)
    s = params.sensor_dim
    return e2e_apply(
        params,
        features[..., : -2 * s],
        features[..., -2 * s : -s],
        features[..., -s:],
    )
