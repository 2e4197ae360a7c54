"""The sample guard: no single sample may poison a calibration stream.

Every row gets a *reason* (:data:`REASONS`, int32 codes): padding is ``masked``; a
non-finite ``w`` or ``x``, or one outside the :class:`SampleCheck` box (the model's
envelope, or the training range widened by a margin), is flagged; so is a step whose
new state or ``theta`` is not finite (e.g. the model did not solve there). A flagged
row is *skipped*: the step is fed the last ok ``(w, x)`` so no NaN enters any
computation, the carried state stays exactly as it was and the outputs repeat the
last ok ones. A stream then continues exactly as if the sample had not arrived.
:func:`guarded_update` is that rule for one sample, shared by the scan of
:func:`~jaxcal.calibrators.interface.run_calibrator` and by single-sample streaming;
``CalOutput.valid`` and ``CalOutput.reason`` report it per row, :func:`count_reasons`
counts it for reports.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.programs.packed import Packing
from jaxcal.typedefs import Array

CalState = Any  # a calibrator's state pytree (see :mod:`jaxcal.calibrators.interface`)
CalStepOutput = Any  # its per-step outputs: ``theta``, ``xhat``, ``aux``


# Why a row was or was not used; the int32 code of a reason is its index (codes are
# stored in result files: new reasons go at the end). The input checks take precedence
# in the order of sample_reason (a NaN w hides a NaN x on the same row).
REASONS = (
    "ok",
    "masked",  # padding (mask False)
    "w_nonfinite",  # NaN / Inf in the operating conditions
    "x_nonfinite",  # NaN / Inf in the measurements
    "w_out_of_range",  # outside SampleCheck.w_low .. w_high
    "x_out_of_range",  # outside SampleCheck.x_low .. x_high
    "state_nonfinite",  # the step itself gave a non-finite theta or state
    "x_partial",  # some outputs missing (NaN) and the calibrator needs them all
    "outlier",  # a wild reading, flagged by the front door's screening (outliers.py)
)
REASON_CODE = {name: code for code, name in enumerate(REASONS)}
OK, MASKED, STATE_NONFINITE = 0, 1, REASON_CODE["state_nonfinite"]
FLAG_REASONS = REASONS[2:]  # what reports count (ok and padding are not flags)


class SampleCheck(NamedTuple):
    """The valid input box of a calibrator; ``inf`` bounds turn a check off.

    Attributes:
        w_low, w_high: ``[Wd]`` bounds of the operating conditions.
        x_low, x_high: ``[S]`` bounds of the measurements, or ``None`` (not checked).
    """

    w_low: Array
    w_high: Array
    x_low: Array | None = None
    x_high: Array | None = None

    @classmethod
    def from_range(cls, w_low, w_high, x_low=None, x_high=None, *, margin=0.0):
        """A box ``[low - margin * span, high + margin * span]`` per entry.

        "Far outside the training range" is the training min/max widened by
        ``margin`` times its span (``span = high - low``) on each side.

        Args:
            w_low, w_high: ``[Wd]``; x_low, x_high: ``[S]`` or ``None``.
            margin: ``>= 0`` fraction of the span added on each side.

        Returns:
            :class:`SampleCheck` of float64 numpy arrays.
        """
        if not margin >= 0:
            raise ValueError(
                f"SampleCheck.from_range: margin must be >= 0, got {margin}"
            )

        def widen(low, high, name):
            low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
            if low.ndim != 1 or low.shape != high.shape or np.any(low > high):
                raise ValueError(
                    f"SampleCheck.from_range: {name}_low and {name}_high must be [N] "
                    f"with low <= high; got {low.tolist()} and {high.tolist()}"
                )
            span = high - low
            return low - margin * span, high + margin * span

        w_box = widen(w_low, w_high, "w")
        x_box = (None, None) if x_low is None else widen(x_low, x_high, "x")
        return cls(*w_box, *x_box)


def is_partial(x: Array) -> Array:
    """``[]`` bool: ``x [S]`` has some outputs missing (NaN) and the others finite.

    A row with an Inf, or with no finite output, is not partial: it is
    ``x_nonfinite``. Jittable, vmappable.
    """
    missing = jnp.isnan(x)
    return jnp.any(missing) & jnp.all(jnp.isfinite(x) | missing) & ~jnp.all(missing)


def sample_reason(
    check: SampleCheck | None, w: Array, x: Array, *, partial_ok: bool = False
) -> Array:
    """The reason code of one sample before any step (jittable, vmappable).

    Args:
        check: the valid box, or ``None`` (finiteness only).
        w: ``[Wd]``. x: ``[S]``.
        partial_ok: static; the calibrator updates on the observed outputs of a
            partial row (``Calibrator.accepts_partial``): such a row is ``ok``
            (its observed outputs are range-checked), else ``x_partial``.

    Returns:
        ``[]`` int32: ``OK`` or the first failing input check of :data:`REASONS`.
    """
    partial = is_partial(x)
    codes = [REASON_CODE["w_nonfinite"], REASON_CODE["x_nonfinite"]]
    bad = [~jnp.all(jnp.isfinite(w)), ~jnp.all(jnp.isfinite(x)) & ~partial]
    if not partial_ok:
        codes.append(REASON_CODE["x_partial"])
        bad.append(partial)
    if check is not None:
        codes.append(REASON_CODE["w_out_of_range"])
        bad.append(jnp.any((w < check.w_low) | (w > check.w_high)))
        if check.x_low is not None:
            codes.append(REASON_CODE["x_out_of_range"])
            # a missing (NaN) output compares False: only observed ones are checked
            bad.append(jnp.any((x < check.x_low) | (x > check.x_high)))
    reason = jnp.asarray(OK, jnp.int32)
    for code, flag in reversed(list(zip(codes, bad, strict=True))):
        reason = jnp.where(flag, jnp.int32(code), reason)
    return reason


class GuardCarry(NamedTuple):
    """What a guarded stream carries between samples."""

    state: CalState  # the calibrator's state after the last ok sample
    out: CalStepOutput  # outputs of the last ok sample (zeros before any)
    w: Array  # [Wd] last ok w (fed to the step on a flagged sample)
    x: Array  # [S] last ok x


def initial_carry(step: Callable, state: CalState, w: Array, x: Array) -> GuardCarry:
    """A guarded stream's carry before its first ok sample: ``state``, zero outputs
    of ``step``'s shapes and dtypes (what ``run_calibrator`` outputs on leading
    padding) and the placeholder ``(w, x)`` a flagged first sample is fed."""
    out_shape = jax.eval_shape(step, state, w, x)[1]
    out = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), out_shape)
    return GuardCarry(state=state, out=out, w=w, x=x)


def _all_finite(tree) -> Array:
    """``[]`` bool: every float leaf of ``tree`` is finite (keys, ints ignored).

    One reduction per float dtype over the leaves concatenated, not one per leaf:
    the same answer, and on XLA's CPU runtime each reduction is a kernel of its own
    (a stream's step pays a microsecond or two for each)."""
    by_dtype: dict = {}
    for leaf in jax.tree.leaves(tree):
        if jnp.issubdtype(leaf.dtype, jnp.inexact):
            by_dtype.setdefault(leaf.dtype, []).append(jnp.ravel(leaf))
    checks = [jnp.all(jnp.isfinite(jnp.concatenate(v))) for v in by_dtype.values()]
    return jnp.all(jnp.stack(checks)) if checks else jnp.asarray(True)


def guarded_update(
    step: Callable, carry: GuardCarry, w_t: Array, x_t: Array, reason_t: Array
) -> tuple[GuardCarry, CalStepOutput, Array]:
    """One sample through ``step`` unless it is flagged (the rule of the module doc).

    Args:
        step: ``calibrator.step``.
        carry: :class:`GuardCarry` after the previous sample.
        w_t: ``[Wd]``. x_t: ``[S]``.
        reason_t: ``[]`` int32 from :func:`sample_reason` (or ``MASKED``).

    Returns:
        ``(carry, out, reason)``: ``out`` is the new outputs if the row is ok, else
        ``carry.out`` unchanged; ``reason`` adds ``state_nonfinite`` to ``reason_t``.
    """
    return probed_update(step, carry, w_t, x_t, reason_t, False)[:3]


def probed_update(
    step: Callable, carry: GuardCarry, w_t: Array, x_t: Array, reason_t: Array,
    probe_t: Array,
) -> tuple[GuardCarry, CalStepOutput, Array, CalStepOutput]:  # fmt: skip
    """:func:`guarded_update`, and a row that is not used but ``probe_t`` (a
    skipped row whose own values are fine) is still fed to ``step``: its fresh
    outputs say how the row looks to the state before it, while the carry moves on
    exactly as if it had not come. Costs nothing: the step runs at every row anyway
    (on the last ok sample where the row is not used).

    Returns:
        ``(carry, out, reason, fresh)``: ``fresh`` the step's outputs at this row
        (meaningful where the row was used or probed).
    """
    ok = reason_t == OK
    # never feed a flagged value to the model (the NaNs of a partial row reach only
    # a calibrator that accepts them: its reason is ok only then)
    feed = ok | probe_t
    w_in = jnp.where(feed, w_t, carry.w)
    x_in = jnp.where(feed, x_t, carry.x)
    new_state, new_out = step(carry.state, w_in, x_in)
    finite = _all_finite((new_state, new_out.theta))
    reason = jnp.where(ok & ~finite, jnp.int32(STATE_NONFINITE), reason_t)
    ok = reason == OK
    carry = keep_where(ok, GuardCarry(new_state, new_out, w_in, x_in), carry)
    return carry, carry.out, reason.astype(jnp.int32), new_out


def keep_where(ok: Array, new, old):
    """``new`` where ``ok`` else ``old``, leaf by leaf, as one select per dtype on
    the packed leaves (:mod:`jaxcal.calibrators.programs.packed`): a select per leaf is
    a kernel per leaf on XLA's CPU runtime, a dozen or more per sample."""
    packing = Packing.of(old)
    kept = [
        jnp.where(ok, a, b)
        for a, b in zip(packing.pack(new), packing.pack(old), strict=True)
    ]
    return packing.unpack(tuple(kept))


def count_reasons(reason, mask=None) -> dict[str, int]:
    """Host-side counts of flagged samples per reason (for every report).

    Args:
        reason: ``[...]`` int codes (``CalOutput.reason``).
        mask: same shape, True on real samples; ``None`` counts all.

    Returns:
        ``{reason: count}`` for every name of :data:`FLAG_REASONS` (zeros included).
    """
    reason = np.asarray(reason)
    if mask is not None:
        reason = reason[np.asarray(mask, bool)]
    counts = np.bincount(reason.ravel().astype(np.int64), minlength=len(REASONS))
    return {name: int(counts[REASON_CODE[name]]) for name in FLAG_REASONS}
