"""Each method of :func:`jaxcal.calibrate` built from a the problem.

The model-based methods (UKF, least squares) work on the restricted model
``F(w, theta_declared) -> x_used`` with outputs normalised by their *noise* std, so
their measurement-noise setting is simply ``r = 1``; parameters are scaled by the
half-width of the box and start at the nominal values. The E2E network learns the
inverse of the model from simulations over the box at the data's own operating
conditions ("E2E-sim"). A trained policy is loaded from its run folder.

Every method returns the same ``Calibrator(init, step)`` and is run by one jitted
fleet runner with the problem's sample check (non-finite samples and samples outside
the model's valid input box are skipped and flagged). A row with some outputs missing
is used by the UKF and least squares on its observed outputs and skipped by E2E and
a policy (reason ``x_partial``; :mod:`jaxcal.calibrators.guard`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import (
    Calibrator,
    SampleCheck,
    SensorNorm,
    run_fleet,
)
from jaxcal.calibrators.policy import range_check
from jaxcal.data.buckets import Buckets
from jaxcal.data.dataset import Padded
from jaxcal.problem import Problem


def model_check(problem: Problem) -> SampleCheck | None:
    """The model's valid input box as a sample check (``None``: finiteness only)."""
    if problem.model.condition_range is None:
        return None
    low, high = problem.model.condition_range
    return SampleCheck(w_low=jnp.asarray(low), w_high=jnp.asarray(high))


def noise_norm(problem: Problem, dtype) -> SensorNorm:
    """Outputs in units of their noise std (so ``r = 1`` is the noise)."""
    return SensorNorm(
        mean=jnp.asarray(problem.norm.x_mean, dtype),
        std=jnp.asarray(problem.noise_std, dtype),
    )


def make_runner(check: SampleCheck | None, key=None):
    """``run(calibrator, padded, skip=None) -> CalOutput``: the fleet scan, jitted;
    ``skip [U, T]`` bool cells are skipped like padding (the front door relabels
    them ``outlier``)."""

    def run(calibrator: Calibrator, padded: Padded, skip=None):
        fleet = jax.jit(run_fleet, static_argnums=0)
        keys = None
        if key is not None:
            keys = jax.random.split(key, padded.w.shape[0])
        mask = padded.mask if skip is None else padded.mask & ~np.asarray(skip)
        return fleet(
            calibrator,
            jnp.asarray(padded.w),
            jnp.asarray(padded.x),
            jnp.asarray(mask),
            keys=keys,
            check=check,
        )

    return run


def model_based(method: str, problem: Problem, dtype, options: dict) -> Calibrator:
    """UKF or least squares on the problem's model; a model with hidden states gets
    the joint state-and-parameter filter / the moving-window fit (options
    ``state_std``, ``state_q``)."""
    return model_based_factory(method, problem, dtype, options)(
        noise_norm(problem, dtype)
    )


def model_based_factory(
    method: str, problem: Problem, dtype, options: dict
) -> Callable[[SensorNorm], Calibrator]:
    """:func:`model_based` as ``make(norm) -> Calibrator``: every setting taken from
    ``problem`` and ``options`` now, the output normalisation (the noise) left to
    ``make``, which may be called under ``jax.jit`` with a traced noise."""
    from jaxcal.calibrators.least_squares import LeastSquaresConfig, make_least_squares
    from jaxcal.calibrators.ukf import UKFConfig, make_joint_ukf, make_ukf
    from jaxcal.calibrators.window_state import make_window_least_squares

    cfg_type = UKFConfig if method == "ukf" else LeastSquaresConfig
    cfg = cfg_type(r=1.0, **_take(options, cfg_type))
    common = dict(
        theta0=np.asarray(problem.theta_prior, dtype),
        theta_scale=np.asarray(problem.theta_half_width, dtype),
    )
    if not problem.model.is_stateful:
        options.pop("state_std", None), options.pop("state_q", None)
        make = make_ukf if method == "ukf" else make_least_squares
        measure = problem.measure()
        return lambda norm: make(measure, cfg, norm, **common)
    tr = problem.transition()
    states = problem.model.state_names
    scale = state_scale(problem, dtype)
    std = _state_option(options.pop("state_std", None), states, 0.01 * scale)
    box = (problem.theta_low, problem.theta_high)
    if method == "ukf":
        # a floor of process noise on the states (the model is trusted)
        q = _state_option(options.pop("state_q", None), states, 1e-6 * scale)
        return lambda norm: make_joint_ukf(
            tr, cfg, norm, state_std=std, state_q=q, state_scale=scale,
            theta_box=box, **common,
        )  # fmt: skip
    if "state_q" in options:
        raise ValueError("state_q is a UKF option; least squares takes state_std")
    if cfg.prior_std is None:  # a window without excitation must not run off
        cfg = dataclasses.replace(cfg, prior_std=1.0)
    return lambda norm: make_window_least_squares(
        tr, cfg, norm, state_std=np.maximum(std, 1e-9 * scale),
        state_scale=scale, theta_box=box, **common,
    )  # fmt: skip


def state_scale(problem: Problem, dtype) -> np.ndarray:
    """``[Z]`` natural size of each hidden state: ``|z0|`` at the nominal parameters
    and the mid-range conditions (1 where that is 0)."""
    tr = problem.transition()
    w_mid = 0.5 * (problem.input_range.w_low + problem.input_range.w_high)
    theta = jnp.asarray(problem.theta_prior, dtype)
    z0 = np.abs(np.asarray(tr.init(jnp.asarray(w_mid, dtype), theta)))
    return np.where(np.isfinite(z0) & (z0 > 0), z0, 1.0).astype(dtype)


def _state_option(value, states, default) -> np.ndarray:
    """``state_std`` / ``state_q``: a scalar, ``{state: value}`` or ``[Z]`` (state
    units, >= 0) -> ``[Z]``."""
    if value is None:
        return np.asarray(default)
    if isinstance(value, dict):
        unknown = sorted(set(value) - set(states))
        if unknown:
            raise ValueError(
                f"unknown state(s) {unknown}; the model has {list(states)}"
            )
        pairs = zip(states, default, strict=True)
        arr = np.array([float(value.get(n, d)) for n, d in pairs])
    else:
        arr = np.broadcast_to(np.asarray(value, np.float64), (len(states),)).copy()
    if not np.all(np.isfinite(arr) & (arr >= 0)):
        raise ValueError(f"state settings must be finite and >= 0, got {arr.tolist()}")
    return arr.astype(np.asarray(default).dtype)


def ukf_options(method: str, options: dict) -> dict:
    """The settings of a UKF pass over the problem (:mod:`.screen`): the method's
    own when it is the UKF, and the hidden states' ``state_std`` / ``state_q``
    (``options`` is not modified)."""
    from jaxcal.calibrators.ukf import UKFConfig

    names = {"state_std", "state_q"}
    if method == "ukf":
        names |= {f.name for f in dataclasses.fields(UKFConfig)} - {"r"}
    return {k: v for k, v in options.items() if k in names}


def _take(options: dict, cfg_type) -> dict:
    """Pop the options that are fields of ``cfg_type`` (``r`` is fixed at 1)."""
    names = {f.name for f in dataclasses.fields(cfg_type)} - {"r"}
    return {k: options.pop(k) for k in list(options) if k in names}


def _e2e(problem: Problem, buckets: Buckets, seed: int, options: dict) -> Calibrator:
    """A given E2E network, or one trained on simulations of the model (E2E-sim)."""
    from jaxcal.calibrators.e2e import E2EConfig, make_e2e_calibrator
    from jaxcal.nets.mlp import RegressorConfig

    params = options.pop("e2e", None)
    measure = problem.measure() if not problem.model.is_stateful else None
    window = int(options.pop("e2e_window", 16 if measure is None else 0))
    if params is None:
        cfg = options.pop(
            "e2e_config",
            E2EConfig(
                hidden_sizes=(64, 64),
                fit=RegressorConfig(
                    learning_rate=1e-3, batch_size=256, num_epochs=60,
                    validation_fraction=0.1, patience=10,
                ),
            ),
        )  # fmt: skip
        copies = int(options.pop("e2e_copies", 8))
        params = fit_e2e_sim(problem, buckets, cfg, seed, copies, window)[0]
    if measure is not None:
        return make_e2e_calibrator(params, measure)
    return make_e2e_calibrator(
        params, transition=problem.transition(),
        theta0=jnp.asarray(problem.theta_prior, buckets.dtype),
    )  # fmt: skip


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


def fit_e2e_sim(
    problem: Problem, buckets: Buckets, cfg, seed: int, copies: int, window: int = 0
):
    """Train G on ``copies`` simulated fleets: the data's conditions, a constant
    parameter vector per simulated unit drawn uniformly in the box, and Gaussian
    output noise of the problem's std (``window``: G's input, see ``fit_e2e``).
    Simulated group by group of ``buckets`` (memory grows with the rows)."""
    from jaxcal.calibrators.e2e import e2e_training_rows, fit_e2e_rows

    key = jax.random.key(seed)
    key_theta, key_noise, key_fit = jax.random.split(key, 3)
    dtype = buckets.dtype
    sizes = [part.w.shape[0] for part in buckets.parts]
    low, high = problem.theta_low, problem.theta_high
    shape = (copies * sum(sizes), len(low))
    theta_all = np.asarray(
        jax.random.uniform(key_theta, shape, minval=low, maxval=high)
    ).astype(dtype)
    theta_all = theta_all.reshape(copies, sum(sizes), len(low))  # copy-major
    inputs, targets = [], []
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
        rows = e2e_training_rows(w, np.nan_to_num(x), np.array(theta), ok, window)
        inputs.append(rows[0]), targets.append(rows[1])
    return fit_e2e_rows(
        key_fit, np.concatenate(inputs), np.concatenate(targets), cfg,
        condition_dim=len(problem.model.condition_names),
        sensor_dim=len(problem.output_names), window=window,
    )  # fmt: skip


def _policy(problem: Problem, options: dict) -> tuple[Calibrator, SampleCheck | None]:
    """A trained policy from ``run=<folder>`` and its sample check (the run's own
    training range, not the range of the data being calibrated); its names must
    match the problem, and the problem's model must be the run's own (by names and
    by outputs at probe points, :mod:`jaxcal.training.model_check`). With
    ``anchor=<folder>`` (an absolute policy's run with its
    band) the run, an incremental policy, is gated by it (:mod:`jaxcal.calibrators.
    gated`): the feedback while the model fits the data, the anchor where not."""
    # The run loader belongs to the training layer: a trained policy is one of its
    # artefacts (imported here, when the method is asked for, not at import time).
    from jaxcal.training.runs import (
        LoadedRun,
        check_run_model,
        load_calibrator,
        load_run,
        run_check,
    )

    run_dir = options.pop("run", None)
    anchor_dir = options.pop("anchor", None)
    if not run_dir:
        raise ValueError("method='policy' needs run=<trained run folder>")
    run = run_dir if isinstance(run_dir, LoadedRun) else load_run(run_dir)
    _check_run(problem, run)
    check_run_model(run, problem.model)  # the policy runs with the run's own model
    anchor = None
    if anchor_dir:  # the feedback gated by an absolute policy (calibrators.gated)
        anchor = load_run(anchor_dir)
        _check_run(problem, anchor)
        check_run_model(anchor, problem.model)
    return load_calibrator(run, anchor), run_check(run)


def _check_run(problem: Problem, run) -> None:
    """A loaded run's names must match the problem's (else a ValueError)."""
    run_dir = run.run_dir
    names = run.problem.theta_names
    if tuple(names) != problem.theta_names:
        raise ValueError(
            f"run {run_dir} calibrates {list(names)}, not "
            f"{list(problem.theta_names)}: pass theta={list(names)}"
        )
    if run.problem.model.condition_names != problem.model.condition_names:
        raise ValueError(
            f"run {run_dir} was trained on model {run.problem.model.name!r} with "
            f"conditions {list(run.problem.model.condition_names)}, not "
            f"{list(problem.model.condition_names)}"
        )
    outputs = run.problem.output_names
    if tuple(outputs) != problem.output_names:
        raise ValueError(
            f"run {run_dir} uses outputs {list(outputs)}, the data give "
            f"{list(problem.output_names)}: pass outputs={list(outputs)}"
        )


class Built(NamedTuple):
    """A method ready to run (:func:`build_calibrator`)."""

    calibrator: Calibrator
    run: Callable  # run(calibrator, padded, skip=None) -> CalOutput
    prior_std: np.ndarray  # [P] what is known of theta before a stream's first sample


def build_calibrator(
    method: str, problem: Problem, buckets: Buckets, seed: int, options: dict
) -> Built:
    """:class:`Built` of ``method``; unknown options are an error."""
    dtype = buckets.dtype
    prior_std = _prior_std(method, problem, options)
    if method in ("ukf", "ls"):
        cal = model_based(method, problem, dtype, options)
        run = make_runner(model_check(problem))
    elif method == "e2e":
        cal = _e2e(problem, buckets, seed, options)
        run = make_runner(range_check(problem))
    else:
        cal, check = _policy(problem, options)
        run = make_runner(check)
    if options:
        raise ValueError(f"unknown option(s) for method={method!r}: {sorted(options)}")
    return Built(cal, run, prior_std)


def _prior_std(method: str, problem: Problem, options: dict) -> np.ndarray:
    """``[P]`` std of theta before any sample: the UKF's Gaussian prior, else the
    std of a uniform over the box (what the other methods know before data)."""
    from jaxcal.calibrators.ukf import UKFConfig

    half = problem.theta_half_width
    if method == "ukf":
        return float(options.get("prior_std", UKFConfig.prior_std)) * half
    return half / np.sqrt(3.0)
