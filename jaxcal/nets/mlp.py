"""A plain float32 MLP and a generic jitted regression trainer for the supervised nets.

The paper's simulator network D and its end-to-end baseline G are both MLPs with three
hidden layers of 100 ReLU units, a linear output and Xavier (Glorot) initialisation,
trained with Adam on minibatches (Tian et al., appendix "Simulator Network" and "E2E
Network"). This module owns that shared machinery: :class:`MLP`, the per-feature
:class:`Normalizer`, :class:`RegressorParams` (network weights + input/target
statistics, one pytree to checkpoint) and :func:`fit_regressor`.

Training jits one function per epoch that draws a permutation of the training indices
and advances every minibatch in a ``lax.scan``; the host loop over epochs only evaluates
the validation loss, logs, updates a progress bar and applies early stopping (both in
:mod:`jaxcal.nets.epochs`). Networks run in float32 whatever the global precision:
inputs are cast and statistics are stored as float32.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from jaxcal.data.normalisation import column_stats
from jaxcal.nets.epochs import TrainState, chunked_mse, make_train_epoch, run_epochs
from jaxcal.typedefs import Array, PRNGKey, PyTree

ACTIVATIONS: dict[str, Callable[[Array], Array]] = {
    "relu": nn.relu,
    "leaky_relu": nn.leaky_relu,
    "tanh": jnp.tanh,
    "elu": nn.elu,
    "gelu": nn.gelu,
    "silu": nn.silu,
}


class MLP(nn.Module):
    """Fully connected network ``[..., I] -> [..., output_dim]`` with a linear output.

    Attributes:
        hidden_sizes: width of each hidden layer, e.g. ``(100, 100, 100)``.
        output_dim: size of the linear output layer.
        activation: hidden activation, a key of :data:`ACTIVATIONS`.
    """

    hidden_sizes: tuple[int, ...]
    output_dim: int
    activation: str = "relu"

    @nn.compact
    def __call__(self, x: Array) -> Array:
        """``[..., I]`` inputs (cast to float32) to ``[..., output_dim]`` outputs."""
        if self.activation not in ACTIVATIONS:
            raise ValueError(
                f"activation must be one of {sorted(ACTIVATIONS)}, "
                f"got {self.activation!r}"
            )
        act = ACTIVATIONS[self.activation]
        dense = dict(
            kernel_init=nn.initializers.glorot_uniform(),
            bias_init=nn.initializers.zeros,
            dtype=jnp.float32,
            param_dtype=jnp.float32,
        )
        x = x.astype(jnp.float32)
        for i, size in enumerate(self.hidden_sizes):
            x = act(nn.Dense(size, name=f"hidden_{i}", **dense)(x))
        return nn.Dense(self.output_dim, name="output", **dense)(x)


@struct.dataclass
class Normalizer:
    """Per-feature affine standardisation ``z = (v - mean) / std``."""

    mean: Array  # [D] float32
    std: Array  # [D] float32, strictly positive

    def normalize(self, v: Array) -> Array:
        """``[..., D]`` raw values to standardised float32."""
        return (v.astype(jnp.float32) - self.mean) / self.std

    def denormalize(self, z: Array) -> Array:
        """``[..., D]`` standardised values back to raw units."""
        return z * self.std + self.mean


def fit_normalizer(values: Array) -> Normalizer:
    """Mean and std over axis 0 of ``values [N, D]`` (host-side).

    A feature that is (numerically) constant, std at most 1e-6 of its scale, gets
    std 1, so that it passes through centred instead of being blown up by a tiny
    divisor (e.g. a θ component that the data set never varies): the data's
    :func:`~jaxcal.data.normalisation.column_stats`, with a looser threshold, since
    a float32 network cannot resolve a finer spread.
    """
    mean, std = column_stats(values, np.float64, rel=1e-6)
    return Normalizer(
        mean=jnp.asarray(mean, jnp.float32), std=jnp.asarray(std, jnp.float32)
    )


@struct.dataclass
class RegressorParams:
    """Everything a trained regressor needs besides its (static) architecture."""

    net: PyTree  # flax parameters of the MLP
    input_norm: Normalizer  # [I]
    target_norm: Normalizer  # [O]


def regressor_apply(model: nn.Module, params: RegressorParams, inputs: Array) -> Array:
    """Predict targets ``[..., O]`` (target units) from raw inputs ``[..., I]``."""
    z = model.apply({"params": params.net}, params.input_norm.normalize(inputs))
    return params.target_norm.denormalize(z)


@dataclasses.dataclass(frozen=True)
class RegressorConfig:
    """Optimisation settings of :func:`fit_regressor` (the model fixes the layers)."""

    learning_rate: float = 1e-3  # Adam step size
    batch_size: int = 256  # minibatch size (paper appendix: 256)
    num_epochs: int = 100  # upper bound on passes over the training set
    validation_fraction: float = 0.0  # share of samples held out (0: no validation)
    patience: int | None = None  # stop after this many epochs without val improvement
    min_delta: float = 0.0  # improvement below this does not reset the patience

    def __post_init__(self):
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be > 0, got {self.learning_rate}")
        if self.batch_size < 1 or self.num_epochs < 1:
            raise ValueError("batch_size and num_epochs must be >= 1")
        if not 0.0 <= self.validation_fraction < 1.0:
            raise ValueError(
                f"validation_fraction must be in [0, 1), got {self.validation_fraction}"
            )
        if self.patience is not None and self.patience < 1:
            raise ValueError(f"patience must be >= 1 or None, got {self.patience}")
        if self.patience is not None and self.validation_fraction == 0.0:
            raise ValueError("patience (early stopping) needs validation_fraction > 0")


def _check_data(inputs, targets) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(inputs, dtype=np.float32)
    y = np.asarray(targets, dtype=np.float32)
    if x.ndim != 2 or y.ndim != 2 or x.shape[0] != y.shape[0] or x.shape[0] < 1:
        raise ValueError(
            f"inputs must be [N, I] and targets [N, O] with the same N >= 1, "
            f"got {x.shape} and {y.shape}"
        )
    for name, v in (("inputs", x), ("targets", y)):
        if not np.isfinite(v).all():
            row = int(np.argwhere(~np.isfinite(v))[0, 0])
            raise ValueError(f"{name} contain NaN or inf (first at row {row})")
    return x, y


class _Split(NamedTuple):
    """Standardised training and validation arrays and the statistics they used."""

    xn: Array  # [N_train, I]
    yn: Array  # [N_train, O]
    xv: Array  # [N_val, I]
    yv: Array  # [N_val, O]
    input_norm: Normalizer
    target_norm: Normalizer
    num_val: int


def _standardised_split(key: PRNGKey, x, y, validation_fraction: float) -> _Split:
    """Hold out a random ``validation_fraction`` of the rows (none: keep the order)
    and standardise both parts with the training part's statistics."""
    n = x.shape[0]
    num_val = int(round(validation_fraction * n))
    if num_val and n - num_val < 1:
        raise ValueError(f"validation_fraction leaves no training samples (N = {n})")
    order = np.asarray(jax.random.permutation(key, n)) if num_val else np.arange(n)
    train_idx, val_idx = order[: n - num_val], order[n - num_val :]
    input_norm, target_norm = fit_normalizer(x[train_idx]), fit_normalizer(y[train_idx])

    def standardise(v, norm):  # on the host: eager jnp ops would each compile
        return jnp.asarray((v - np.asarray(norm.mean)) / np.asarray(norm.std))

    xn, yn = (
        standardise(x[train_idx], input_norm),
        standardise(y[train_idx], target_norm),
    )
    xv, yv = standardise(x[val_idx], input_norm), standardise(y[val_idx], target_norm)
    return _Split(xn, yn, xv, yv, input_norm, target_norm, num_val)


def fit_regressor(
    key: PRNGKey,
    model: nn.Module,
    inputs: Array,
    targets: Array,
    cfg: RegressorConfig,
    *,
    log_fn: Callable[[int, dict[str, float]], None] | None = None,
    progress: bool = False,
) -> tuple[RegressorParams, dict]:
    """Fit ``model`` to map ``inputs`` to ``targets`` by minibatch Adam on the MSE.

    Inputs and targets are standardised with statistics of the training part; the loss
    is the MSE of normalised targets. With a validation split the returned parameters
    are those of the best validation epoch, and ``cfg.patience`` stops training early.

    Args:
        key: PRNG key (init, validation split and minibatch order).
        model: a flax module mapping ``[B, I]`` to ``[B, O]`` (e.g. :class:`MLP`).
        inputs: ``[N, I]`` raw inputs (cast to float32).
        targets: ``[N, O]`` raw targets.
        cfg: optimisation settings.
        log_fn: called as ``log_fn(epoch, {"train_loss": ..., "val_loss": ...})``.
        progress: show a tqdm bar over epochs.

    Returns:
        ``(params, history)``; ``history`` holds ``train_loss`` and ``val_loss`` arrays
        ``[E]`` (``val_loss`` empty without validation), ``best_epoch``,
        ``epochs_run`` and ``stopped_early``.
    """
    x, y = _check_data(inputs, targets)
    key_split, key_init, key_epochs = jax.random.split(key, 3)
    data = _standardised_split(key_split, x, y, cfg.validation_fraction)
    optimizer = optax.adam(cfg.learning_rate)
    net = jax.jit(model.init)(key_init, data.xn[:1])["params"]
    state = TrainState(net=net, opt_state=optimizer.init(net))
    n_train = data.xn.shape[0]
    batch_size = min(cfg.batch_size, n_train)
    train_epoch = make_train_epoch(model, optimizer, key_epochs, n_train, batch_size)
    val_loss_fn = jax.jit(lambda net, xv, yv: chunked_mse(model, net, xv, yv))
    best_net, train_hist, val_hist, best_epoch = run_epochs(
        train_epoch, val_loss_fn, state, (data.xn, data.yn),
        (data.xv, data.yv) if data.num_val else None, num_epochs=cfg.num_epochs,
        patience=cfg.patience, min_delta=cfg.min_delta, log_fn=log_fn,
        progress=progress,
    )  # fmt: skip
    history = {
        "train_loss": np.asarray(train_hist),
        "val_loss": np.asarray(val_hist),
        "best_epoch": best_epoch,
        "epochs_run": len(train_hist),
        "stopped_early": len(train_hist) < cfg.num_epochs,
    }
    params = RegressorParams(
        net=best_net, input_norm=data.input_norm, target_norm=data.target_norm
    )
    return params, history
