"""E2E-sim: the E2E network trained on simulations of the problem's model.

The data's own operating conditions, a constant parameter vector per simulated unit
drawn uniformly in the box, and Gaussian output noise of the problem's std: the
network learns the inverse of the model where the data will ask it ("E2E-sim").

Its std (:func:`held_out_band`): split conformal on one more simulated fleet the
network never saw, drawn the same way (Lei et al. 2018, sec. 2.2), per bucket of
samples since a unit's start (:mod:`jaxcal.calibrators.uncertainty.conformal`): the 90 %
half-width of ``|theta_hat - theta|`` over 1.6449, with ``theta_hat`` projected into
the box as the calibrator reports it. It covers 90 % of such simulated units: white
noise of the problem's std, a constant theta anywhere in the box; the front door's
misfit check withholds it where the data's innovations say otherwise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.methods.e2e.network import (
    E2EConfig,
    _apply,
    e2e_features,
    e2e_training_rows,
    fit_e2e_rows,
    make_e2e_calibrator,
    window_features,
)
from jaxcal.calibrators.uncertainty.conformal import fit_band
from jaxcal.data.buckets import Buckets
from jaxcal.nets.mlp import RegressorConfig
from jaxcal.problem import Problem


def simulate_fleet(problem: Problem, w: np.ndarray, theta: np.ndarray, mask):
    """``x [U, T, S]`` of the problem's model along ``w [U, T, W]`` with ``theta
    [U, T, P]``: evaluated in parallel for a static model, by ``lax.scan`` from
    ``init(w_0, theta_0)`` for one with memory (invalid rows hold the state)."""
    if not problem.model.is_stateful:
        simulate = jax.jit(jax.vmap(jax.vmap(problem.measure())))
        return np.asarray(simulate(jnp.asarray(w), jnp.asarray(theta)))
    tr = problem.transition()

    def unit(w_u, th_u, m_u):
        def body(z, inputs):
            w_t, th_t, ok = inputs
            z_next, x = tr.step(z, w_t, th_t)
            return jnp.where(ok, z_next, z), x

        return jax.lax.scan(body, tr.init(w_u[0], th_u[0]), (w_u, th_u, m_u))[1]

    run = jax.jit(jax.vmap(unit))
    return np.asarray(run(jnp.asarray(w), jnp.asarray(theta), jnp.asarray(mask)))


def _simulated(problem: Problem, buckets: Buckets, key_theta, key_noise, copies: int):
    """``[(w, x, theta, ok)]`` per group of ``buckets``: ``copies`` simulated fleets
    on the data's conditions, a constant theta per unit drawn uniformly in the box,
    Gaussian output noise of the problem's std (``ok``: the rows to learn from)."""
    dtype = buckets.dtype
    sizes = [part.w.shape[0] for part in buckets.parts]
    low, high = problem.theta_low, problem.theta_high
    shape = (copies * sum(sizes), len(low))
    theta_all = np.asarray(
        jax.random.uniform(key_theta, shape, minval=low, maxval=high)
    ).astype(dtype)
    theta_all = theta_all.reshape(copies, sum(sizes), len(low))  # copy-major
    groups = []
    for b, part in enumerate(buckets.parts):
        start = sum(sizes[:b])
        theta_u = theta_all[:, start : start + sizes[b]].reshape(-1, len(low))
        w = np.concatenate([part.w] * copies)
        mask = np.concatenate([part.mask] * copies)
        theta = np.broadcast_to(theta_u[:, None, :], w.shape[:2] + theta_u.shape[-1:])
        x = simulate_fleet(problem, w, theta, mask)
        key_b = key_noise if b == 0 else jax.random.fold_in(key_noise, b)
        x = x + problem.noise_std * np.asarray(jax.random.normal(key_b, x.shape))
        ok = mask & np.all(np.isfinite(x), axis=-1)
        groups.append((w, np.nan_to_num(x), np.array(theta), ok))
    return groups


def held_out_band(problem: Problem, buckets: Buckets, params, seed: int):
    """The split-conformal band of the trained ``params`` (module doc), on one
    simulated fleet drawn with a key the training never used."""
    key = jax.random.fold_in(jax.random.key(seed), 0x42)  # not a training draw
    key_theta, key_noise = jax.random.split(key)
    hats, truths, masks = [], [], []
    length = max(part.w.shape[1] for part in buckets.parts)
    for w, x, theta, ok in _simulated(problem, buckets, key_theta, key_noise, 1):
        if params.window:
            feats = window_features(w, x, ok, params.window)
        else:
            feats = e2e_features(w, x, ok)
        hat = np.asarray(_apply(params, jnp.asarray(feats), jnp.asarray(x)))
        hat = np.clip(hat, problem.theta_low, problem.theta_high)
        pad = ((0, 0), (0, length - w.shape[1]), (0, 0))
        hats.append(np.pad(hat, pad)), truths.append(np.pad(theta, pad))
        masks.append(np.pad(ok, pad[:2]))
    return fit_band(np.concatenate(hats), np.concatenate(truths), np.concatenate(masks))


def fit_e2e_sim(
    problem: Problem, buckets: Buckets, cfg, seed: int, copies: int, window: int = 0
):
    """Train G on ``copies`` simulated fleets: the data's conditions, a constant
    parameter vector per simulated unit drawn uniformly in the box, and Gaussian
    output noise of the problem's std (``window``: G's input, see ``fit_e2e``).
    Simulated group by group of ``buckets`` (memory grows with the rows)."""
    key = jax.random.key(seed)
    key_theta, key_noise, key_fit = jax.random.split(key, 3)
    inputs, targets = [], []
    for w, x, theta, ok in _simulated(problem, buckets, key_theta, key_noise, copies):
        rows = e2e_training_rows(w, x, theta, ok, window)
        inputs.append(rows[0]), targets.append(rows[1])
    return fit_e2e_rows(
        key_fit, np.concatenate(inputs), np.concatenate(targets), cfg,
        condition_dim=len(problem.model.condition_names),
        sensor_dim=len(problem.output_names), window=window,
    )  # fmt: skip


def e2e_calibrator(problem: Problem, buckets: Buckets, seed: int, cfg):
    """A given E2E network, or one trained on simulations of the model (E2E-sim)."""
    params = cfg.e2e
    measure = problem.measure() if not problem.model.is_stateful else None
    window = cfg.e2e_window
    window = int((16 if measure is None else 0) if window is None else window)
    if params is None:
        fit = cfg.e2e_config or E2EConfig(
            hidden_sizes=(64, 64),
            fit=RegressorConfig(
                learning_rate=1e-3, batch_size=256, num_epochs=60,
                validation_fraction=0.1, patience=10,
            ),
        )  # fmt: skip
        copies = int(cfg.e2e_copies)
        params = fit_e2e_sim(problem, buckets, fit, seed, copies, window)[0]
    # a std only where held-out simulations say what G's error is (not for given
    # weights); every estimate projected into the declared box
    band = held_out_band(problem, buckets, params, seed) if cfg.e2e is None else None
    box = (problem.theta_low, problem.theta_high)
    if measure is not None:
        return make_e2e_calibrator(params, measure, box=box, band=band)
    return make_e2e_calibrator(
        params, transition=problem.transition(),
        theta0=jnp.asarray(problem.theta_prior, buckets.dtype), box=box, band=band,
    )  # fmt: skip
