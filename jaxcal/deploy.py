"""Real-time calibration with a trained run: the deployment API.

A run folder written by ``python -m jaxcal.train`` holds everything a policy needs:
``config.json`` (architecture, dynamics), ``data.json`` (sensor and parameter names)
and ``policy/`` (actor weights, surrogate weights, normalisation and action box, saved
at every checkpoint). No data file and no training code path is needed to deploy::

    from jaxcal.deploy import StreamingCalibrator

    cal = StreamingCalibrator("runs/cmapss-clac-surrogate-s0")
    for w_t, x_t in stream:                  # w_t [W] (alt, Mach, TRA, T2), x_t [S]
        theta_t = cal.step(w_t, x_t)         # [P] numpy, one jitted call
    theta, xhat = cal.run(w, x, mask)        # batch: [U, T, W], [U, T, S], [U, T]

Guarded samples: a sample with NaN / Inf in ``w`` or ``x``, or far outside the run's
training range (:func:`jaxcal.calibrators.policy.range_check`), is *skipped*: the
carried state is left exactly as it was, ``step`` returns the last valid theta
(zeros, the healthy prior, before any valid sample) and the flag is readable
(``cal.last_valid``, ``cal.last_reason``, :meth:`StreamingCalibrator.step_info`;
``run(..., return_flags=True)``). The stream then continues as if the sample had
never arrived. Runs trained before the range was stored check finiteness only.

Semantics (:mod:`jaxcal.calibrators.policy`): the calibrator carries the model output
x-hat internally; each sample gives theta_t = box(pi*(norm(x-hat_{t-1}), norm(x_t),
norm(w_t))) and x-hat_t = D(w_t, x-hat_{t-1}, theta_t) (or F with ``dynamics=physics``).
:func:`load_calibrator` returns the same method as a
:class:`~jaxcal.calibrators.interface.Calibrator`, so it runs beside the baselines through
``run_calibrator`` / ``run_fleet``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.agents.networks import make_networks
from jaxcal.calibrators.interface import REASONS, Calibrator, SampleCheck
from jaxcal.calibrators.policy import (
    PolicyParams,
    initial_guard_carry,
    make_fleet_runner,
    make_guarded_stream_step,
    make_policy_calibrator,
    range_check,
)
from jaxcal.checkpoint import Checkpointer, load_config
from jaxcal.config import TrainConfig
from jaxcal.envs.tracking import Dynamics
from jaxcal.precision import enable_x64
from jaxcal.surrogate.model import init_surrogate_params
from jaxcal.training.problem import RunMeta, make_agent, make_dynamics
from jaxcal.training.run_dir import DATA_FILE, POLICY_BEST_DIR, POLICY_DIR, read_json


class LoadedRun(NamedTuple):
    """A trained policy ready to run.

    Attributes:
        run_dir: the run folder.
        config: its resolved :class:`~jaxcal.config.TrainConfig`.
        meta: sensor / parameter names, engine.
        params: the deployable :class:`PolicyParams`.
        actor: the actor module (static).
        dynamics: the transition x-hat_t = D(w_t, x-hat_{t-1}, theta_t) (static).
        step: the checkpoint step (chunks trained) the policy comes from.
    """

    run_dir: Path
    config: TrainConfig
    meta: RunMeta
    params: PolicyParams
    actor: nn.Module
    dynamics: Dynamics
    step: int


def load_run(
    run_dir: str | os.PathLike, *, which: str = "selected", step: int | None = None
) -> LoadedRun:
    """Load a run's policy.

    Args:
        run_dir: the run folder.
        which: ``"selected"``: the policy the run kept (``budget.select``: the best
            validation tracking RMSE, or the last one); ``"last"``: the latest
            checkpoint.
        step: a specific checkpoint step of ``which`` (``None``: the newest).

    Raises:
        FileNotFoundError: the folder is not a run, or it has no policy checkpoint.
        ValueError: the checkpoint does not match the run's config.
    """
    run_dir = Path(run_dir)
    cfg = load_config(run_dir, TrainConfig)
    meta = RunMeta.from_json(read_json(run_dir / DATA_FILE))
    if cfg.dynamics == "physics":
        enable_x64()
    dtype = jnp.float64 if cfg.dynamics == "physics" else jnp.float32
    dims = (meta.condition_dim, len(meta.sensors), len(meta.theta_names))
    agent = make_agent(cfg.agent, 2 * dims[1] + dims[0], dims[2])

    def abstract(key):
        dyn = (
            init_surrogate_params(key, *dims, cfg.surrogate)
            if cfg.dynamics == "surrogate"
            else None
        )
        return PolicyParams(
            actor=agent.init(key).actor.params,
            dyn_params=dyn,
            w_mean=jnp.zeros(dims[0], dtype),
            w_std=jnp.ones(dims[0], dtype),
            x_mean=jnp.zeros(dims[1], dtype),
            x_std=jnp.ones(dims[1], dtype),
            theta_low=jnp.zeros(dims[2], dtype),
            theta_high=jnp.ones(dims[2], dtype),
        )

    if which not in ("selected", "last"):
        raise ValueError(f"which must be 'selected' or 'last', got {which!r}")
    target = jax.eval_shape(abstract, jax.random.key(0))
    folder = run_dir / POLICY_DIR
    best = run_dir / POLICY_BEST_DIR
    if which == "selected" and cfg.budget.select != "last" and best.is_dir():
        folder = best
    with Checkpointer(folder) as ckpt:
        if ckpt.latest_step() is None:
            raise FileNotFoundError(
                f"{folder} holds no policy checkpoint; train the run "
                "first (python -m jaxcal.train ...)"
            )
        step = ckpt.latest_step() if step is None else step
        params = ckpt.restore(step, target)
    return LoadedRun(
        run_dir=run_dir,
        config=cfg,
        meta=meta,
        params=params,
        actor=make_networks(cfg.agent, dims[2]).actor,
        dynamics=make_dynamics(cfg.dynamics, meta),
        step=int(step),
    )


def run_check(run: LoadedRun) -> SampleCheck | None:
    """The run's valid input box (training range + margin; ``None``: finiteness).

    Pass it as ``check=`` to ``run_calibrator`` / ``run_fleet`` / the fleet paths.
    """
    return range_check(run.meta)


def load_calibrator(run_dir: str | os.PathLike | LoadedRun) -> Calibrator:
    """The run's policy as a ``Calibrator(init, step)`` (pure functions, not jitted).

    Use it like any baseline: ``jax.jit(run_fleet, static_argnums=0)(cal, w, x, m)``,
    with ``check=run_check(run)`` to flag samples outside the training range.
    """
    run = run_dir if isinstance(run_dir, LoadedRun) else load_run(run_dir)
    return make_policy_calibrator(run.actor, run.dynamics, run.params)


class StepInfo(NamedTuple):
    """One streamed sample's result."""

    theta: np.ndarray  # [P] this sample's theta, or the last valid one if skipped
    valid: bool  # the sample was used
    reason: str  # "ok" or why it was skipped (jaxcal.calibrators.interface.REASONS)


class StreamingCalibrator:
    """Sample-by-sample calibration with host numpy in and out (jitted inside).

    Args:
        run: a run folder or a :class:`LoadedRun`.

    Attributes:
        sensors: the S sensor names ``x`` must follow, in order.
        theta_names: the P parameter names of ``theta``.
        check: the valid input box (:func:`run_check`), ``None``: finiteness only.
        last_valid, last_reason: the flag of the last :meth:`step` (``None`` after
            :meth:`reset`).
    """

    def __init__(self, run: str | os.PathLike | LoadedRun):
        self.run_info = run if isinstance(run, LoadedRun) else load_run(run)
        self.sensors = self.run_info.meta.sensors
        self.theta_names = self.run_info.meta.theta_names
        self._params = self.run_info.params
        self._dtype = np.dtype(self._params.x_mean.dtype)
        self.check = run_check(self.run_info)
        # placed once: a numpy box would be copied to the device on every step
        self._check_dev = jax.tree.map(jnp.asarray, self.check)
        actor, dynamics = self.run_info.actor, self.run_info.dynamics
        self._step = make_guarded_stream_step(actor, dynamics)
        self._run = make_fleet_runner(actor, dynamics)
        self._carry0 = initial_guard_carry(actor, dynamics, self._params)
        self.reset()

    def reset(self) -> None:
        """Forget the carried model output (start a new stream)."""
        self._carry = self._carry0
        self.last_valid: bool | None = None
        self.last_reason: str | None = None

    def _check(self, name: str, value, size: int, ndim: int) -> np.ndarray:
        try:
            array = np.asarray(value, dtype=self._dtype)
        except (TypeError, ValueError):
            raise ValueError(
                f"{name} must be numeric with {ndim} dimension(s) of last size {size}"
            ) from None
        if array.ndim != ndim or array.shape[-1] != size:
            raise ValueError(
                f"{name} must have {ndim} dimension(s) with last size {size}, got "
                f"shape {array.shape}"
            )
        return array

    def step_info(self, w, x) -> StepInfo:
        """Calibrate on one sample and say whether it was used.

        Args:
            w: ``[W]`` (alt, Mach, TRA, T2). x: ``[S]``.

        Returns:
            :class:`StepInfo`; a skipped sample leaves the state untouched.
        """
        w = self._check("w", w, self.run_info.meta.condition_dim, 1)
        x = self._check("x", x, len(self.sensors), 1)
        self._carry, out, reason = self._step(
            self._params, self._carry, w, x, self._check_dev
        )
        self.last_reason = REASONS[int(reason)]
        self.last_valid = self.last_reason == "ok"
        return StepInfo(np.asarray(out.theta), self.last_valid, self.last_reason)

    def step(self, w, x) -> np.ndarray:
        """Calibrate on one sample: ``w [W]`` (alt, Mach, TRA, T2) and ``x [S]``.

        Returns:
            ``theta [P]`` (numpy) for this sample; the last valid one when the
            sample is skipped (see ``last_valid`` / ``last_reason``).
        """
        return self.step_info(w, x).theta

    def run(self, w, x, mask=None, *, return_flags: bool = False) -> tuple:
        """Calibrate whole trajectories: ``lax.scan`` over time, vmapped over units.

        Args:
            w: ``[U, T, W]``; x: ``[U, T, S]``; mask: ``[U, T]`` valid samples
                (``None``: all valid). Padded and flagged samples repeat the last
                valid outputs.
            return_flags: also return the per-sample flags.

        Returns:
            ``(theta [U, T, P], xhat [U, T, S])`` numpy arrays, plus
            ``(valid [U, T] bool, reason [U, T] int32)`` with ``return_flags``
            (codes into ``jaxcal.calibrators.interface.REASONS``; padding is
            ``masked``).
        """
        w = self._check("w", w, self.run_info.meta.condition_dim, 3)
        x = self._check("x", x, len(self.sensors), 3)
        if mask is None:
            mask = np.ones(w.shape[:2], bool)
        mask = np.asarray(mask, bool)
        if mask.shape != w.shape[:2] or x.shape[:2] != w.shape[:2]:
            raise ValueError(
                f"w {w.shape}, x {x.shape} and mask {mask.shape} must share [U, T]"
            )
        out = self._run(self._params, w, x, mask, self._check_dev)
        theta, xhat = np.asarray(out.theta), np.asarray(out.xhat)
        if return_flags:
            return theta, xhat, np.asarray(out.valid), np.asarray(out.reason)
        return theta, xhat
