"""Sample-by-sample calibration with a trained run: :class:`StreamingCalibrator`.

Host numpy in and out, one jitted call per sample (or one per batch of whole
trajectories). Guarded samples: a sample with NaN / Inf in ``w`` or ``x``, or far
outside the run's training range
(:func:`jaxcal.calibrators.methods.policy.calibrator.range_check` of the
run's problem), is *skipped*: the carried state is left exactly as it was, ``step``
returns the last valid theta (before any valid sample the theta the stream starts from,
inside the box:
:func:`~jaxcal.calibrators.methods.policy.calibrator.stream_start_theta`) and the flag
is readable (``last_valid``, ``last_reason``, :meth:`StreamingCalibrator.step_info`;
``run(..., return_flags=True)``). A sample with some outputs missing (NaN in some of
``x``, the others finite) is skipped the same way with reason ``x_partial``: a policy
needs every output
(:func:`~jaxcal.calibrators.methods.policy.calibrator.make_policy_calibrator`); the UKF
and least squares of :func:`jaxcal.calibrate` and :mod:`jaxcal.fleet` use such samples.
Users import it from :mod:`jaxcal.deploy`.
"""

from __future__ import annotations

import functools
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import (
    OK,
    REASONS,
    GuardCarry,
    guarded_update,
    initial_carry,
    run_fleet,
    sample_reason,
)
from jaxcal.calibrators.methods.policy.calibrator import (
    initial_guard_carry,
    make_fleet_runner,
    make_guarded_stream_step,
)
from jaxcal.calibrators.methods.policy.gated import DEFAULT_WINDOW, gate_state
from jaxcal.calibrators.methods.policy.trained import (
    LoadedRun,
    load_calibrator,
    load_run,
    run_check,
)
from jaxcal.calibrators.programs.packed import (
    Packing,
    dispatch_is_synchronous,
    jit_per_row,
)
from jaxcal.envs.memory import HintedDynamics


class StepInfo(NamedTuple):
    """One streamed sample's result."""

    theta: np.ndarray  # [P] this sample's theta, or the last valid one if skipped
    valid: bool  # the sample was used
    reason: str  # "ok" or why it was skipped (jaxcal.calibrators.interface.REASONS)
    # [P] std of theta from the run's calibrated band (None: the run has none)
    theta_std: np.ndarray | None = None
    # with an anchor: whether the model fit the data (the feedback's theta is used)
    gate_open: bool | None = None


class StreamingCalibrator:
    """Sample-by-sample calibration with host numpy in and out (jitted inside).

    Args:
        run: a run folder or a :class:`LoadedRun`.
        anchor: an absolute policy's run (with its ``uncertainty.json``) that takes
            over where the model misfits the data; ``run`` must then be an
            incremental policy (:mod:`jaxcal.calibrators.methods.policy.gated`).
        trust_code: run the runs' model code (a copy of a model file, a module)
            given as folders: the user trusts them (``docs/trust.md``).

    Attributes:
        conditions: the W condition names ``w`` must follow, in order.
        sensors: the S output names ``x`` must follow, in order.
        theta_names: the P parameter names of ``theta``.
        check: the valid input box (:func:`run_check`), ``None``: finiteness only.
        last_valid, last_reason: the flag of the last :meth:`step` (``None`` after
            :meth:`reset`).
        synchronous: JAX runs each step on the calling thread
            (:func:`jaxcal.deploy.synchronous_dispatch`, called at the program's
            start: about half the cost of a small model's step).
    """

    def __init__(
        self,
        run: str | os.PathLike | LoadedRun,
        anchor: str | os.PathLike | LoadedRun | None = None,
        *,
        trust_code: bool = False,
    ):
        self.run_info = load_run(run, trust_code=trust_code)
        self.synchronous = dispatch_is_synchronous()
        problem = self.run_info.problem
        self.sensors = problem.output_names
        self.theta_names = problem.theta_names
        self.conditions = problem.model.condition_names
        # placed on the device once: a checkpoint's leaves are host numpy, and a
        # numpy argument is copied to the device on every call (the actor's weights,
        # ~0.3 MB, at every sample: most of a small model's step)
        self._params = jax.device_put(self.run_info.params)
        self._dtype = np.dtype(self._params.x_mean.dtype)
        self.check = run_check(self.run_info)
        # placed once: a numpy box would be copied to the device on every step
        self._check_dev = jax.tree.map(jnp.asarray, self.check)
        actor, dynamics = self.run_info.actor, self.run_info.dynamics
        # a warm-started solve keeps XLA's default schedule (jit_per_row)
        self._warm_solve = isinstance(dynamics, HintedDynamics)
        # the model's solver starts from the previous sample's solution (a
        # turbofan's Newton solve), one sample per call and along whole trajectories
        self._step = make_guarded_stream_step(actor, dynamics, warm_start=True)
        self._run = make_fleet_runner(actor, dynamics)
        self._band = jax.device_put(self.run_info.band)
        self._carry0 = initial_guard_carry(
            actor, dynamics, self._params, self._band, warm_start=True
        )
        self.anchor_info = (
            None if anchor is None else load_run(anchor, trust_code=trust_code)
        )
        if self.anchor_info is not None:
            self._gated(self._carry0)
        self._stream = _PackedStream(
            self._step,
            Packing.of(self._carry0),
            (self._params, self._check_dev, self._band),
            len(self.conditions),
            warm_solve=self._warm_solve,
        )
        self._packed0 = jax.device_put(Packing.of(self._carry0).pack(self._carry0))
        self.reset()

    def _gated(self, carry: GuardCarry) -> None:
        """Step and batch run of the gated calibrator (same call signatures; the
        runs' params are constants of its one compiled program)."""
        stream = load_calibrator(self.run_info, self.anchor_info, warm_start=True)
        cal = load_calibrator(self.run_info, self.anchor_info)
        an = self.anchor_info
        an_state = initial_guard_carry(
            an.actor, an.dynamics, an.params, an.band, warm_start=True
        ).state
        state = gate_state(carry.state, an_state, DEFAULT_WINDOW, carry.x.dtype)
        carry0 = initial_carry(stream.step, state, carry.w, carry.x)
        # before any valid sample: the policy's start theta, as the ungated stream
        out0 = carry0.out._replace(theta=carry.out.theta.astype(carry0.out.theta.dtype))
        self._carry0 = carry0._replace(out=out0)

        @jax.jit  # called inside _PackedStream's program, which has the options
        def step(carry, w, x, check):
            reason = sample_reason(check, w, x)
            return guarded_update(stream.step, carry, w, x, reason)

        @jax.jit
        def run(w, x, mask, check):
            return run_fleet(cal, w, x, mask, check=check)

        self._step = lambda _, carry, w, x, check, __: step(carry, w, x, check)
        self._run = lambda _, w, x, mask, check, __: run(w, x, mask, check)

    def reset(self) -> None:
        """Forget the carried model output (start a new stream)."""
        self._carry = self._packed0
        self.last_valid: bool | None = None
        self.last_reason: str | None = None

    def _check(self, name: str, value, size: int, ndim: int) -> np.ndarray:
        if (  # the common case, without numpy's conversion (a stream's every call)
            type(value) is np.ndarray
            and value.dtype == self._dtype
            and value.ndim == ndim
            and value.shape[-1] == size
        ):
            return value
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

    def _advance(self, w, x) -> tuple:
        """One sample through the stream: ``(theta, theta_std, gate_open)``; the
        flag in ``last_valid`` / ``last_reason``."""
        w = self._check("w", w, len(self.conditions), 1)
        x = self._check("x", x, len(self.sensors), 1)
        self._carry, theta, reason, std, gate = self._stream(self._carry, w, x)
        self.last_reason = REASONS[reason]
        self.last_valid = reason == OK
        return theta, std, gate

    def step_info(self, w, x) -> StepInfo:
        """Calibrate on one sample and say whether it was used.

        Args:
            w: ``[W]`` the model's conditions (``conditions``). x: ``[S]``
                (``sensors``).

        Returns:
            :class:`StepInfo`; a skipped sample leaves the state untouched.
        """
        theta, std, gate = self._advance(w, x)
        return StepInfo(theta, self.last_valid, self.last_reason, std, gate)

    def step(self, w, x) -> np.ndarray:
        """Calibrate on one sample: ``w [W]`` (``conditions``) and ``x [S]``.

        Returns:
            ``theta [P]`` (numpy) for this sample; the last valid one when the
            sample is skipped (see ``last_valid`` / ``last_reason``).
        """
        return self._advance(w, x)[0]

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
        w = self._check("w", w, len(self.conditions), 3)
        x = self._check("x", x, len(self.sensors), 3)
        if mask is None:
            mask = np.ones(w.shape[:2], bool)
        mask = np.asarray(mask, bool)
        if mask.shape != w.shape[:2] or x.shape[:2] != w.shape[:2]:
            raise ValueError(
                f"w {w.shape}, x {x.shape} and mask {mask.shape} must share [U, T]"
            )
        out = self._run(self._params, w, x, mask, self._check_dev, self._band)
        theta, xhat = np.asarray(out.theta), np.asarray(out.xhat)
        if return_flags:
            return theta, xhat, np.asarray(out.valid), np.asarray(out.reason)
        return theta, xhat


class _PackedStream:
    """``step`` with few arguments and one read a sample: on XLA's CPU runtime each
    argument and result of a call costs about as much as a small kernel (parsed,
    checked, allocated), and each host read waits and copies on its own.

    * the carry in per-dtype buffers (:mod:`jaxcal.calibrators.programs.packed`);
    * the run's constants (params, check, band: two dozen leaves) in per-dtype
      buffers placed on the device once, a weight matrix of 4096 numbers or more in
      a buffer of its own (not copied out of a shared one at every call); they stay
      arguments, not constants of the program, so XLA folds nothing the fleet
      runner computes at run time (the stream and the fleet give the same bits);
    * the sample's ``w`` and ``x`` as one row;
    * what the host reads (theta, the band's std, the reason, the gate) as one
      array of theta's dtype (the reason's code and the gate's flag are small
      integers, exact in it).

    ``__call__(buffers, w, x) -> (buffers, theta, reason, theta_std or None,
    gate_open or None)``, host numpy out.
    """

    def __init__(self, step, packing: Packing, consts, num_w: int, *, warm_solve=False):
        const_packing = Packing.of(consts, alone_from=4096)
        self._consts = jax.device_put(const_packing.pack(consts))
        layout: list = []  # (offset, size) of theta, std, reason, gate in the read

        @functools.partial(jit_per_row, warm_solve=warm_solve)
        def packed(consts, buffers, row):
            params, check, band = const_packing.unpack(consts)
            w, x = row[:num_w], row[num_w:]
            carry = packing.unpack(buffers)
            carry, out, reason = step(params, carry, w, x, check, band)
            aux = out.aux if isinstance(out.aux, dict) else {}
            dtype = out.theta.dtype
            parts = [out.theta, aux.get("theta_std"), reason, aux.get("gate_open")]
            layout.clear()
            offset = 0
            for part in parts:
                size = None if part is None else int(np.size(part))
                layout.append(None if part is None else (offset, size))
                offset += size or 0
            read = jnp.concatenate(
                [jnp.ravel(p).astype(dtype) for p in parts if p is not None]
            )
            return packing.pack(carry), read

        self._jitted = packed
        self._layout = layout
        self._slots: tuple | None = None  # the layout's slices, once traced

    def __call__(self, buffers, w: np.ndarray, x: np.ndarray):
        buffers, read = self._jitted(self._consts, buffers, np.concatenate((w, x)))
        read = np.asarray(read)  # the one transfer to the host
        if self._slots is None:
            self._slots = tuple(
                None if slot is None else slice(slot[0], slot[0] + slot[1])
                for slot in self._layout
            )
        theta, std, reason, gate = self._slots
        return (
            buffers,
            read[theta],
            int(read[reason.start]),
            None if std is None else read[std],
            None if gate is None else bool(read[gate.start]),
        )
