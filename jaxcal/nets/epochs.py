"""The training loop of :func:`jaxcal.nets.mlp.fit_regressor`.

One jitted function per epoch draws a permutation of the training indices and
advances every minibatch in a ``lax.scan`` (:func:`make_train_epoch`); the host loop
over epochs (:func:`run_epochs`) only evaluates the validation loss (in chunks,
:func:`chunked_mse`), logs, updates a progress bar and applies early stopping.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from jaxcal.progress import progress_bar
from jaxcal.typedefs import Array, PRNGKey, PyTree

EVAL_CHUNK = 8192  # rows per chunk when scoring large sets, to bound activation memory


@struct.dataclass
class TrainState:
    """The network's parameters and Adam's state between minibatch steps."""

    net: PyTree
    opt_state: optax.OptState


def chunked_mse(model: nn.Module, net: PyTree, xn: Array, yn: Array) -> Array:
    """Mean squared error on normalised data, scored in chunks (bounded memory)."""
    n = xn.shape[0]
    chunk = min(n, EVAL_CHUNK)
    num_chunks = -(-n // chunk)
    pad = num_chunks * chunk - n
    weight = jnp.pad(jnp.ones(n, jnp.float32), (0, pad)).reshape(num_chunks, chunk)
    xs = jnp.pad(xn, ((0, pad), (0, 0))).reshape(num_chunks, chunk, -1)
    ys = jnp.pad(yn, ((0, pad), (0, 0))).reshape(num_chunks, chunk, -1)

    def chunk_sse(args):
        x, y, w = args
        err = model.apply({"params": net}, x) - y
        return jnp.sum(w[:, None] * err**2)

    return jnp.sum(jax.lax.map(chunk_sse, (xs, ys, weight))) / (n * yn.shape[1])


def make_train_epoch(
    model: nn.Module, optimizer, key_epochs: PRNGKey, n_train: int, batch_size: int
):
    """``train_epoch(state, epoch, xn, yn) -> (state, mean loss)``, jitted: one pass
    of minibatch Adam over a permutation drawn from ``fold_in(key_epochs, epoch)``."""
    num_batches = n_train // batch_size  # the remainder changes with every permutation

    def loss_fn(net, xb, yb):
        return jnp.mean((model.apply({"params": net}, xb) - yb) ** 2)

    def sgd_step(state, batch_idx, xn, yn):
        loss, grads = jax.value_and_grad(loss_fn)(
            state.net, xn[batch_idx], yn[batch_idx]
        )
        updates, opt_state = optimizer.update(grads, state.opt_state, state.net)
        return TrainState(optax.apply_updates(state.net, updates), opt_state), loss

    @jax.jit
    def train_epoch(state, epoch, xn, yn):
        key = jax.random.fold_in(key_epochs, epoch)
        perm = jax.random.permutation(key, n_train)[: num_batches * batch_size]
        batches = perm.reshape(num_batches, batch_size)
        state, losses = jax.lax.scan(
            lambda s, b: sgd_step(s, b, xn, yn), state, batches
        )
        return state, jnp.mean(losses)

    return train_epoch


def run_epochs(
    train_epoch,
    val_loss_fn,
    state: TrainState,
    train: tuple[Array, Array],
    val: tuple[Array, Array] | None,
    *,
    num_epochs: int,
    patience: int | None,
    min_delta: float,
    log_fn,
    progress: bool,
):
    """The epoch loop: keeps the best validation epoch's parameters (the last epoch's
    without validation) and stops after ``patience`` epochs without improvement.

    Args:
        train_epoch: from :func:`make_train_epoch`; val_loss_fn: ``(net, xv, yv) ->
            loss``; state: the initial :class:`TrainState`.
        train: (xn, yn) standardised training arrays; val: (xv, yv), or ``None``
            without validation.
        num_epochs, patience, min_delta: as in ``RegressorConfig``.
        log_fn: called as ``log_fn(epoch, record)`` (or ``None``); progress: show a
            tqdm bar.

    Returns:
        (best parameters, train losses, validation losses, best epoch).

    Raises:
        FloatingPointError: a loss became NaN or inf.
    """
    train_hist, val_hist = [], []
    best_net, best_val, best_epoch, since_best = state.net, math.inf, 0, 0
    bar = progress_bar(range(num_epochs), disable=not progress, desc="fit", leave=False)
    for epoch in bar:
        state, train_loss = train_epoch(state, epoch, *train)
        record = {"train_loss": float(train_loss)}
        if val is not None:
            record["val_loss"] = float(val_loss_fn(state.net, *val))
        if not all(math.isfinite(v) for v in record.values()):
            raise FloatingPointError(
                f"loss became non-finite at epoch {epoch}: {record}"
            )
        train_hist.append(record["train_loss"])
        if val is not None:
            val_hist.append(record["val_loss"])
            if record["val_loss"] < best_val - min_delta:
                best_net, best_val, best_epoch = state.net, record["val_loss"], epoch
                since_best = 0
            else:
                since_best += 1
        else:
            best_net, best_epoch = state.net, epoch
        bar.set_postfix(record)
        if log_fn is not None:
            log_fn(epoch, record)
        if patience is not None and since_best >= patience:
            break
    return best_net, train_hist, val_hist, best_epoch
