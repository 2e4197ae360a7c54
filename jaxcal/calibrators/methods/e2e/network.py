"""End-to-end (E2E) baseline: a network that maps measurements straight to parameters.

Tian et al. §2.4, eq. "e2e": θ_t = G(w_t, x_t, x_{t−1}), with G an MLP of three hidden
layers of 100 ReLU units, linear output, Adam at learning rate 1e-4 (appendix "E2E
Network" and the hyper-parameter table). It is supervised: the paper trains it on the
labelled units 1, 4, 7 and 9 of Dataset #1, whose flights do not cover the envelope of
the test units — the weakness the paper points out. "E2E-sim" is the same network
trained on simulated labels over the whole envelope; both are this module with other
training data, chosen by the caller.

Inputs are [w_t, x_t, x_{t−1}] standardised with training statistics; at a unit's first
valid sample x_{t−1} is taken equal to x_t. :func:`make_e2e_calibrator` wraps a trained
network in the common :class:`~jaxcal.calibrators.interface.Calibrator` interface.

A row with some outputs missing (NaN: a sensor channel dropped out) cannot enter G,
and is skipped with reason ``x_partial`` (the calibrator does not accept partial
rows): the estimate holds, the row is flagged ``partial``. Imputing the missing
output with the model at the current θ was not chosen: G would read back the value
its own last estimate implies, which pulls θ_t towards θ_{t−1} by an amount nobody
controls, and G was trained on complete rows only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxcal.calibrators.interface import Calibrator, CalStepOutput, MeasureFn
from jaxcal.calibrators.uncertainty.conformal import band_std
from jaxcal.nets.mlp import (
    MLP,
    Normalizer,
    RegressorConfig,
    RegressorParams,
    fit_regressor,
    regressor_apply,
)
from jaxcal.typedefs import Array, PRNGKey


@dataclasses.dataclass(frozen=True)
class E2EConfig:
    """Architecture and fitting settings of the E2E network (paper appendix)."""

    hidden_sizes: tuple[int, ...] = (100, 100, 100)  # paper: n1 = n2 = n3 = 100
    activation: str = "relu"  # paper: ReLU hidden layers, identity output
    fit: RegressorConfig = RegressorConfig(
        learning_rate=1e-4,  # paper table: "Learning rate - E2E"
        batch_size=256,
        num_epochs=200,
        validation_fraction=0.1,
        patience=20,
    )


@struct.dataclass
class E2EParams:
    """Trained G: weights and statistics (leaves) plus its static shape."""

    regressor: RegressorParams
    hidden_sizes: tuple[int, ...] = struct.field(pytree_node=False)
    activation: str = struct.field(pytree_node=False)
    condition_dim: int = struct.field(pytree_node=False)  # W
    sensor_dim: int = struct.field(pytree_node=False)  # S
    theta_dim: int = struct.field(pytree_node=False)  # P
    # 0: the paper's inputs [w_t, x_t, x_{t-1}]; K >= 1: the last K samples
    # [w_t, x_t, ..., w_{t-K+1}, x_{t-K+1}] (models with memory).
    window: int = struct.field(pytree_node=False, default=0)

    @property
    def network(self) -> MLP:
        """The (parameter-free) flax module of G, rebuilt from the static fields."""
        return MLP(self.hidden_sizes, self.theta_dim, self.activation)


def init_e2e_params(
    key: PRNGKey, condition_dim: int, sensor_dim: int, theta_dim: int, cfg: E2EConfig
) -> E2EParams:
    """A fresh G with identity normalisation (e.g. a ``jax.eval_shape`` target)."""
    in_dim = condition_dim + 2 * sensor_dim
    net = MLP(tuple(cfg.hidden_sizes), theta_dim, cfg.activation)
    weights = jax.jit(net.init)(key, jnp.zeros((1, in_dim), jnp.float32))["params"]

    def identity(d):
        return Normalizer(mean=jnp.zeros(d, jnp.float32), std=jnp.ones(d, jnp.float32))

    return E2EParams(
        regressor=RegressorParams(weights, identity(in_dim), identity(theta_dim)),
        hidden_sizes=tuple(cfg.hidden_sizes),
        activation=cfg.activation,
        condition_dim=condition_dim,
        sensor_dim=sensor_dim,
        theta_dim=theta_dim,
    )


def e2e_features(w: Array, x: Array, mask: Array | None = None) -> Array:
    """Stack [w_t, x_t, x_{t−1}] along time (axis −2), x_{t−1} = x_t where undefined.

    Args:
        w: ``[..., T, W]`` operating conditions.
        x: ``[..., T, S]`` measurements.
        mask: optional ``[..., T]`` validity; x_{t−1} is replaced by x_t at t = 0 and
            wherever sample t − 1 is invalid (the first valid sample of a unit).

    Returns:
        ``[..., T, W + 2S]``.
    """
    x_prev = jnp.concatenate([x[..., :1, :], x[..., :-1, :]], axis=-2)
    if mask is not None:
        mask = jnp.asarray(mask, bool)
        prev_valid = jnp.concatenate([mask[..., :1] & False, mask[..., :-1]], axis=-1)
        x_prev = jnp.where(prev_valid[..., None], x_prev, x)
    return jnp.concatenate([w, x, x_prev], axis=-1)


def window_features(w: Array, x: Array, mask: Array | None, window: int) -> Array:
    """Stack the last ``window`` samples ``[w_t, x_t, w_{t-1}, x_{t-1}, ...]`` along
    time; a sample before the unit's first valid one (or an invalid one) is replaced
    by the next more recent sample, as :func:`e2e_features` does for ``x_{t-1}``.

    Returns:
        ``[..., T, window (W + S)]``.
    """
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    if mask is None:
        mask = jnp.ones(x.shape[:-1], bool)
    mask = jnp.asarray(mask, bool)
    cur = jnp.concatenate([w, x], axis=-1)
    blocks, prev = [cur], cur
    for k in range(1, window):  # a static, small loop over lags, not over time
        shifted = jnp.concatenate(
            [jnp.repeat(cur[..., :1, :], k, axis=-2), cur[..., :-k, :]], axis=-2
        )
        ok = jnp.concatenate(
            [jnp.zeros(mask.shape[:-1] + (k,), bool), mask[..., :-k]], axis=-1
        )
        prev = jnp.where(ok[..., None], shifted, prev)
        blocks.append(prev)
    return jnp.concatenate(blocks, axis=-1)


def _input_dim(condition_dim: int, sensor_dim: int, window: int) -> int:
    if window == 0:
        return condition_dim + 2 * sensor_dim
    return window * (condition_dim + sensor_dim)


def _apply(params: E2EParams, inputs: Array, like: Array) -> Array:
    expected = _input_dim(params.condition_dim, params.sensor_dim, params.window)
    if inputs.shape[-1] != expected:
        raise ValueError(
            f"e2e: expected {expected} inputs (W = {params.condition_dim}, S = "
            f"{params.sensor_dim}, window = {params.window}), got {inputs.shape[-1]}"
        )
    theta = regressor_apply(params.network, params.regressor, inputs)
    dtype = jnp.result_type(like) if jnp.issubdtype(like.dtype, jnp.floating) else None
    return theta if dtype is None else theta.astype(dtype)


def e2e_apply(params: E2EParams, w_t: Array, x_t: Array, x_prev: Array) -> Array:
    """θ_t = G(w_t, x_t, x_{t−1}) for any leading batch shape; ``[..., P]``."""
    if params.window:
        raise ValueError("e2e_apply takes the paper's inputs; this G has a window")
    return _apply(params, jnp.concatenate([w_t, x_t, x_prev], axis=-1), x_t)


def fit_e2e(
    key: PRNGKey,
    w: Array,
    x: Array,
    theta: Array,
    mask: Array,
    cfg: E2EConfig,
    *,
    log_fn: Callable[[int, dict[str, float]], None] | None = None,
    progress: bool = False,
    window: int = 0,
) -> tuple[E2EParams, dict]:
    """Fit G on labelled trajectories (supervised; Tian et al. §2.4).

    Args:
        key: PRNG key (initialisation, validation split, minibatch order).
        w: ``[U, T, W]`` operating conditions of the labelled units.
        x: ``[U, T, S]`` their measurements.
        theta: ``[U, T, P]`` their true parameters (the labels).
        mask: ``[U, T]`` validity; only valid samples are used.
        cfg: architecture and optimisation settings.
        log_fn: per-epoch callback ``log_fn(epoch, {"train_loss", "val_loss"})``.
        progress: show a progress bar.
        window: 0 for the paper's inputs, ``K`` for the last ``K`` samples.

    Returns:
        ``(params, history)`` as in :func:`jaxcal.nets.mlp.fit_regressor`.
    """
    inputs, targets = e2e_training_rows(w, x, theta, mask, window)
    return fit_e2e_rows(
        key, inputs, targets, cfg, condition_dim=np.shape(w)[-1],
        sensor_dim=np.shape(x)[-1], window=window, log_fn=log_fn, progress=progress,
    )  # fmt: skip


def e2e_training_rows(
    w: Array, x: Array, theta: Array, mask: Array, window: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """G's inputs and labels of the valid samples of labelled trajectories.

    Args:
        w, x, theta, mask: as in :func:`fit_e2e` (``[U, T, ·]``, ``[U, T]``).
        window: as in :func:`fit_e2e`.

    Returns:
        ``(inputs [M, F], targets [M, P])`` of the ``M`` valid samples, unit-major.
    """
    w, x, theta = (np.asarray(v) for v in (w, x, theta))
    mask = np.asarray(mask, bool)
    for name, v in (("w", w), ("x", x), ("theta", theta)):
        if v.ndim != 3 or v.shape[:2] != mask.shape:
            raise ValueError(f"{name} must be [U, T, ·] with [U, T] = {mask.shape}")
    if window:
        feats = jax.jit(window_features, static_argnums=3)(w, x, mask, window)
    else:
        feats = jax.jit(e2e_features)(w, x, mask)  # one compile, not many
    features = np.asarray(feats)
    keep = mask.reshape(-1)
    inputs = features.reshape(-1, features.shape[-1])[keep]
    return inputs, theta.reshape(-1, theta.shape[-1])[keep]


def fit_e2e_rows(
    key: PRNGKey,
    inputs: np.ndarray,
    targets: np.ndarray,
    cfg: E2EConfig,
    *,
    condition_dim: int,
    sensor_dim: int,
    window: int = 0,
    log_fn: Callable[[int, dict[str, float]], None] | None = None,
    progress: bool = False,
) -> tuple[E2EParams, dict]:
    """Fit G on rows of :func:`e2e_training_rows` (``W``, ``S`` and ``window`` name
    its input layout); returns as :func:`fit_e2e`."""
    net = MLP(tuple(cfg.hidden_sizes), targets.shape[-1], cfg.activation)
    regressor, history = fit_regressor(
        key, net, inputs, targets, cfg.fit, log_fn=log_fn, progress=progress
    )
    params = E2EParams(
        regressor=regressor,
        hidden_sizes=tuple(cfg.hidden_sizes),
        activation=cfg.activation,
        condition_dim=int(condition_dim),
        sensor_dim=int(sensor_dim),
        theta_dim=targets.shape[-1],
        window=int(window),
    )
    return params, history


@struct.dataclass
class E2EState:
    """Streaming state of the E2E calibrator: the previous samples (and the model
    state that goes with x-hat, for a model with memory)."""

    x_prev: Array  # [S]
    w_hist: Array  # [K - 1, W] the samples before t, most recent first ([0, W]: none)
    x_hist: Array  # [K - 1, S]
    z: Array  # [Z] model state of x-hat ([0] for a static model)
    count: Array  # [] int32 samples used before this one (the band's bucket)


def make_e2e_calibrator(
    params: E2EParams, measure: MeasureFn | None = None, *, transition=None,
    theta0: Array | None = None, box: tuple[Array, Array] | None = None,
    band=None,
) -> Calibrator:  # fmt: skip
    """The E2E network as a :class:`Calibrator` (``init``/``step`` pure functions).

    Args:
        params: trained G.
        measure: optional model ``F(w [W], theta [P]) -> x [S]``; when given, ``xhat``
            is F(w_t, θ_t). Without it ``xhat`` is NaN: G has no model output of its
            own, and a zero or a copy of x_t would make tracking errors look perfect.
        transition: for a model with memory, ``Problem.transition()`` instead of
            ``measure``: ``xhat`` is the model run with the estimated θ, its state
            starting at ``init(w0, theta0)``.
        theta0: ``[P]`` parameters of that initial state.
        box: ``(low [P], high [P])``: G's output is projected into the declared
            box (a network extrapolates past the labels it was trained on).
        band: a :class:`~jaxcal.calibrators.uncertainty.conformal.ThetaBand` fitted on
            held-out simulated units (:func:`jaxcal.calibrators.methods.e2e.simulated.
            held_out_band`): ``aux["theta_std"]`` is its std at the sample's
            count since the unit's first one; ``None``: no std.

    Returns:
        ``Calibrator(init, step)``; ``init`` stores x_{−1} = x_0 (the window holds
        copies of the first sample), so streaming output equals the network's
        prediction over the whole record at once.
    """
    lags = max(params.window - 1, 0)

    def init(key, w0, x0):
        del key  # deterministic
        w0, x0 = jnp.asarray(w0), jnp.asarray(x0)
        z = jnp.zeros((0,), x0.dtype)
        if transition is not None:
            z = transition.init(w0, jnp.asarray(theta0, x0.dtype))
        return E2EState(
            x_prev=x0, w_hist=jnp.tile(w0, (lags, 1)), x_hist=jnp.tile(x0, (lags, 1)),
            z=z, count=jnp.zeros((), jnp.int32),
        )  # fmt: skip

    def step(state, w_t, x_t):
        if params.window:
            blocks = [jnp.concatenate([w_t, x_t])]
            blocks += [
                jnp.concatenate([state.w_hist[i], state.x_hist[i]]) for i in range(lags)
            ]
            theta = _apply(params, jnp.concatenate(blocks), x_t)
        else:
            theta = e2e_apply(params, w_t, x_t, state.x_prev)
        if box is not None:
            theta = jnp.clip(theta, *(jnp.asarray(b, theta.dtype) for b in box))
        z = state.z
        if transition is not None:
            z, xhat = transition.step(state.z, w_t, theta)
        elif measure is None:
            xhat = jnp.full_like(x_t, jnp.nan, dtype=jnp.result_type(x_t, 0.0))
        else:
            xhat = measure(w_t, theta)
        new_state = E2EState(
            x_prev=x_t,
            w_hist=jnp.concatenate([w_t[None], state.w_hist])[:lags],
            x_hist=jnp.concatenate([x_t[None], state.x_hist])[:lags],
            z=z,
            count=state.count + 1,
        )
        aux = None
        if band is not None:
            aux = {"theta_std": band_std(band, state.count).astype(theta.dtype)}
        return new_state, CalStepOutput(theta=theta, xhat=xhat, aux=aux)

    return Calibrator(init=init, step=step)
