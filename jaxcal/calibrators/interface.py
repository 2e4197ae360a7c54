"""The common calibrator interface shared by every calibration method.

A *calibrator* turns a stream of operating conditions ``w_t`` and measurements ``x_t``
into calibrated parameters ``theta_t`` and the model output ``xhat_t`` that goes with
them. Every method in jaxcal — the UKF and sliding-window least squares
(``jaxcal.calibrators``), the end-to-end network ``theta_t = G(w_t, x_t, x_{t-1})``
(paper eq. e2e) and a trained RL policy ``theta_{t+1} = pi(xhat_t, x_{t+1}, w_{t+1})``
— is the same two pure functions, in the optax style::

    class Calibrator(NamedTuple):
        init: (key | None, w0 [Wd], x0 [S]) -> CalState
        step: (state: CalState, w_t [Wd], x_t [S]) -> (CalState, CalStepOutput)

Contract for implementers:

* ``init(key, w0, x0)`` builds the state before the first sample. ``key`` is a PRNG key
  or ``None`` (deterministic methods ignore it). ``(w0, x0)`` is the first valid sample
  of the stream, offered for methods that need a "previous" sample: the E2E network
  stores ``x_prev = x0``, the RL policy starts ``xhat = x0`` (or ``D``/``F`` of it).
  The UKF and least squares ignore it except for shapes. Prior parameter values and
  other settings are closed over by the factory, not passed here.
* ``step(state, w_t, x_t)`` consumes exactly one sample and returns the new state and
  ``CalStepOutput(theta [P], xhat [S], aux)``. ``theta`` is the estimate *at time t*
  (after seeing ``x_t``); ``xhat`` is the model output the method associates with it
  (UKF: ``F(w_t, theta_t)``; RL: ``D(w_t, xhat_{t-1}, theta_t)``; E2E:
  ``F(w_t, theta_t)`` if a model is available). ``aux`` is ``None`` or a dict of
  fixed-shape per-step diagnostics (e.g. ``{"theta_std": [P]}``) with the same keys on
  every step.
* ``step`` is pure and deterministic given its state: a stochastic method carries its
  own PRNG key in its state and splits it inside ``step``. No Python control flow on
  traced values, static shapes, no jit inside (callers jit at entry points).
* RL mapping: with ``state.xhat = xhat_{t-1}``, ``step`` computes
  ``theta_t = pi(xhat_{t-1}, x_t, w_t)`` and ``xhat_t = D(w_t, xhat_{t-1}, theta_t)``,
  i.e. the paper's ``theta_{t+1} = pi(xhat_t, x_{t+1}, w_{t+1})`` shifted by one index.

:func:`run_calibrator` scans ``step`` over a padded record with a validity mask and
:func:`run_fleet` vmaps it over units.

Guarded samples: no single sample may poison a stream; the rule lives in
:mod:`jaxcal.calibrators.guard` and both runners apply it (``CalOutput.valid`` and
``CalOutput.reason`` report it per row). A row with some outputs missing (NaN) is
used by a calibrator with ``accepts_partial`` and skipped as ``x_partial`` by the
others; ``CalOutput.partial`` marks it either way.

A method on the model works on the declared parameters and the used outputs
(``Problem.measure()``). A ``Calibrator`` is hashable (a tuple of functions), so jit
the runners with it as a static argument:
``jax.jit(run_fleet, static_argnums=0)(calibrator, w, x, mask)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxcal.calibrators.guard import (  # noqa: F401 (re-exported: one import path)
    MASKED,
    OK,
    REASON_CODE,
    REASONS,
    GuardCarry,
    SampleCheck,
    count_reasons,
    guarded_update,
    initial_carry,
    is_partial,
    probed_update,
    sample_reason,
)
from jaxcal.typedefs import Array, Metrics, PRNGKey

CalState = Any  # any pytree; each calibrator defines its own state dataclass
MeasureFn = Callable[[Array, Array], Array]  # (w [Wd], theta [P]) -> x [S]


class Measurement(NamedTuple):
    """The measurement model of the UKF and least squares: how an output is compared.

    Both compare an output (measured or predicted) as ``(x - centre) / noise_std``
    and then assume a noise of std ``r`` (their config's) in those units: the
    measurement noise std is ``r * noise_std`` per output, the UKF's measurement
    covariance ``R = diag((r * noise_std)^2)``, the least-squares residual unit
    ``r * noise_std``. The front door passes the measurement noise std itself with
    ``r = 1`` (:mod:`jaxcal.calibrators.programs.compiled`); the paper's methods pass
    the outputs' training std with ``r = 0.01``. ``centre`` only shifts the compared
    values (residuals are differences), e.g. the outputs' training mean.
    """

    centre: Array  # [S]
    noise_std: Array  # [S], > 0


class CalStepOutput(NamedTuple):
    """What one calibrator step reports."""

    theta: Array  # [P] calibrated parameters at time t
    xhat: Array  # [S] model output belonging to theta at time t
    aux: Metrics | None = None  # optional per-step diagnostics, fixed keys and shapes


class CalOutput(NamedTuple):
    """Time-major results of :func:`run_calibrator` (a leading ``[U]`` for fleets)."""

    theta: Array  # [T, P]
    xhat: Array  # [T, S]
    aux: Metrics | None = None  # each entry [T, ...]
    valid: Array | None = None  # [T] bool: the row was used (reason "ok")
    reason: Array | None = None  # [T] int32 code into REASONS
    # [T] bool: some outputs of the row were missing (NaN); used if valid (the
    # calibrator updated on the observed ones), else skipped as "x_partial"
    partial: Array | None = None


class Calibrator(NamedTuple):
    """A calibration method as a pair of pure functions (see the module docstring).

    ``accepts_partial``: ``step`` takes an ``x_t`` with NaN in some outputs (missing)
    and updates on the observed ones only, with fixed shapes (the UKF, least
    squares). When False (the default) the runners skip such rows with reason
    ``x_partial``, so ``step`` never sees a NaN.
    """

    init: Callable[[PRNGKey | None, Array, Array], CalState]
    step: Callable[[CalState, Array, Array], tuple[CalState, CalStepOutput]]
    accepts_partial: bool = False


def run_calibrator(
    calibrator: Calibrator,
    w: Array,
    x: Array,
    mask: Array | None = None,
    *,
    key: PRNGKey | None = None,
    unroll: int = 1,
    check: SampleCheck | None = None,
    probe: Array | None = None,
) -> CalOutput:
    """Run a calibrator over one padded record with ``lax.scan``, guarded.

    Every row gets a reason up front (:func:`sample_reason`, vmapped; masked rows are
    ``masked``; a partial row is ``ok`` only for a calibrator that accepts it). A row
    that is not ok does not advance the state and repeats the previous outputs; the
    step is fed the last ok ``(w, x)`` instead, so a model is never evaluated at
    padding or at a bad sample. Rows before the first ok one output zeros. ``init``
    receives the first ok sample. Not jitted: jit the caller, e.g.
    ``jax.jit(run_calibrator, static_argnums=0)``.

    Args:
        calibrator: the method.
        w: operating conditions, ``[T, Wd]``.
        x: measurements, ``[T, S]``.
        mask: validity, ``[T]`` bool; ``None`` means all valid.
        key: PRNG key handed to ``calibrator.init`` (``None`` for deterministic ones).
        unroll: ``lax.scan`` unroll factor (8 speeds up cheap steps).
        check: the valid input box; ``None`` checks finiteness only.
        probe: ``[T]`` bool or ``None``: rows left out by ``mask`` that the step
            still sees, from the state before them, without using them
            (:func:`~jaxcal.calibrators.guard.probed_update`; only rows whose own
            values pass the checks).

    Returns:
        ``CalOutput`` with ``theta [T, P]``, ``xhat [T, S]``, ``aux`` entries
        ``[T, ...]``, ``valid [T]``, ``reason [T]`` and ``partial [T]``. Sums over
        time must use ``valid`` (held rows repeat). With ``probe``,
        ``aux["fresh"]`` holds the step's own ``aux`` at every row used or probed
        (NaN elsewhere).
    """
    w, x, mask = _check_record(w, x, mask)
    partial_ok = calibrator.accepts_partial
    own = jax.vmap(
        lambda w_t, x_t: sample_reason(check, w_t, x_t, partial_ok=partial_ok)
    )(w, x)
    reason = jnp.where(mask, own, jnp.int32(MASKED))
    first = jnp.argmax(reason == OK)  # the first ok row (0 if none is)
    # nan_to_num is the identity on an ok row; it only matters when no row is ok.
    w0, x0 = jnp.nan_to_num(w[first]), jnp.nan_to_num(x[first])
    state0 = calibrator.init(key, w0, x0)
    out_shape = jax.eval_shape(calibrator.step, state0, w0, x0)[1]
    out0 = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), out_shape)

    def body(carry, inputs):
        carry, out, reason_t = guarded_update(calibrator.step, carry, *inputs)
        return carry, (out, reason_t)

    carry0 = GuardCarry(state0, out0, w0, x0)
    aux = {}
    if probe is None:
        _, (outs, reason) = lax.scan(body, carry0, (w, x, reason), unroll=unroll)
    else:
        probe = probe & (own == OK)
        outs, reason, aux["fresh"] = _probed_scan(
            calibrator.step, carry0, (w, x, reason, probe), unroll
        )
    return CalOutput(
        theta=outs.theta, xhat=outs.xhat, aux={**outs.aux, **aux} if aux else outs.aux,
        valid=reason == OK,
        reason=reason, partial=jax.vmap(is_partial)(x) & mask,
    )  # fmt: skip


def _probed_scan(step, carry0, rows, unroll):
    """:func:`run_calibrator`'s scan with the probed rows fed too; also returns the
    step's own ``aux`` at every row used or probed (NaN elsewhere)."""

    def body(carry, inputs):
        _, _, reason_in, probe_t = inputs
        carry, out, reason_t, fresh = probed_update(step, carry, *inputs)
        seen = (reason_in == OK) | probe_t
        fresh = jax.tree.map(lambda a: jnp.where(seen, a, jnp.nan), fresh.aux)
        return carry, (out, reason_t, fresh)

    return lax.scan(body, carry0, rows, unroll=unroll)[1]


def run_fleet(
    calibrator: Calibrator,
    w: Array,
    x: Array,
    mask: Array | None = None,
    *,
    keys: PRNGKey | None = None,
    unroll: int = 1,
    check: SampleCheck | None = None,
    probe: Array | None = None,
) -> CalOutput:
    """:func:`run_calibrator` vmapped over units.

    Args:
        calibrator: the method.
        w: ``[U, T, Wd]``.
        x: ``[U, T, S]``.
        mask: ``[U, T]`` bool or ``None`` (all valid).
        keys: ``[U]`` PRNG keys, or ``None`` for deterministic calibrators.
        unroll: ``lax.scan`` unroll factor.
        check: the valid input box shared by every unit (``None``: finiteness).
        probe: ``[U, T]`` bool or ``None``: rows to probe (:func:`run_calibrator`).

    Returns:
        ``CalOutput`` with ``theta [U, T, P]``, ``xhat [U, T, S]``, ``aux [U, T, ...]``,
        ``valid [U, T]``, ``reason [U, T]``, ``partial [U, T]``.
    """
    w, x = jnp.asarray(w), jnp.asarray(x)
    if w.ndim != 3 or x.ndim != 3 or w.shape[:2] != x.shape[:2]:
        raise ValueError(
            f"run_fleet: expected w [U, T, Wd] and x [U, T, S] with equal U, T; got "
            f"w {w.shape}, x {x.shape}"
        )
    if mask is None:
        mask = jnp.ones(w.shape[:2], bool)
    mask = jnp.asarray(mask)
    if mask.shape != w.shape[:2]:
        raise ValueError(
            f"run_fleet: mask must be [U, T] = {w.shape[:2]}, got {mask.shape}"
        )

    def one(w_u, x_u, m_u, key_u, probe_u):
        return run_calibrator(
            calibrator, w_u, x_u, m_u, key=key_u, unroll=unroll, check=check,
            probe=probe_u,
        )  # fmt: skip

    axes = (0, 0, 0, None if keys is None else 0, None if probe is None else 0)
    return jax.vmap(one, in_axes=axes)(w, x, mask, keys, probe)


def _check_record(w, x, mask):
    """Shape checks for one record: w [T, Wd], x [T, S], mask [T] (default all)."""
    w, x = jnp.asarray(w), jnp.asarray(x)
    if w.ndim != 2 or x.ndim != 2 or w.shape[0] != x.shape[0]:
        raise ValueError(
            "expected w [T, Wd] and x [T, S] with equal T; "
            f"got w {w.shape}, x {x.shape}"
        )
    if mask is None:
        mask = jnp.ones(w.shape[:1], bool)
    mask = jnp.asarray(mask)
    if mask.shape != w.shape[:1]:
        raise ValueError(f"mask must be [T] = {w.shape[:1]} bool, got {mask.shape}")
    return w, x, mask.astype(bool)


def check_measurement(measurement: Any, name: str = "measurement") -> Measurement:
    """Validate a :class:`Measurement` (``.centre`` and ``.noise_std``, both ``[S]``).

    Args:
        measurement: a :class:`Measurement` (or anything with those two fields).
        name: the argument name used in error messages.

    Returns:
        A :class:`Measurement` of arrays. Value checks (``centre`` finite,
        ``noise_std > 0``) run only when the arrays are concrete, so the function is
        safe under ``jit``/``vmap``.
    """
    if not (hasattr(measurement, "centre") and hasattr(measurement, "noise_std")):
        raise ValueError(
            f"{name} must have .centre and .noise_std arrays of shape [S] "
            "(a Measurement)"
        )
    centre = jnp.asarray(measurement.centre)
    noise_std = jnp.asarray(measurement.noise_std)
    if centre.ndim != 1 or centre.shape != noise_std.shape:
        raise ValueError(
            f"{name}.centre and {name}.noise_std must both be [S]; "
            f"got {centre.shape}, {noise_std.shape}"
        )
    concrete = not any(isinstance(a, jax.core.Tracer) for a in (centre, noise_std))
    if concrete and not (
        np.all(np.isfinite(np.asarray(centre))) and np.all(np.asarray(noise_std) > 0)
    ):
        raise ValueError(f"{name}: centre must be finite and noise_std > 0 everywhere")
    return Measurement(centre=centre, noise_std=noise_std)


def check_prior(theta0: Array, theta_scale: Array | None) -> tuple[Array, Array]:
    """``theta0`` as a float ``[P]`` array and its ``[P]`` scales (ones when None)."""
    theta0 = jnp.asarray(theta0, dtype=jnp.result_type(float))
    if theta0.ndim != 1:
        raise ValueError(f"theta0 must be [P], got shape {theta0.shape}")
    return theta0, check_scale(theta_scale, theta0.shape[0], theta0.dtype)


# A projected estimate stays this share of the box's width inside it: a model
# singular at its bound (a division by theta - low) is still finite there.
BOX_MARGIN = 1e-6


def inner_box(theta_box: tuple[Array, Array] | None, scale: Array):
    """``(low [P], high [P])`` in scaled units (``theta / scale``), each
    :data:`BOX_MARGIN` of the width inside ``theta_box``; ``None`` without a box.
    The UKF's mean and least squares' steps are projected onto it."""
    if theta_box is None:
        return None
    low, high = (jnp.asarray(b, scale.dtype) / scale for b in theta_box)
    margin = BOX_MARGIN * (high - low)
    return low + margin, high - margin


def check_scale(theta_scale: Array | None, num_params: int, dtype: Any) -> Array:
    """``theta_scale`` -> a positive ``[P]`` array (ones when ``None``).

    Args:
        theta_scale: ``[P]`` per-parameter scales or ``None``.
        num_params: ``P``.
        dtype: float dtype of the result.

    Returns:
        ``[P]`` scales. The positivity check runs only on concrete values.
    """
    if theta_scale is None:
        return jnp.ones((num_params,), dtype)
    scale = jnp.asarray(theta_scale, dtype=dtype)
    if scale.shape != (num_params,):
        raise ValueError(
            f"theta_scale must be [P] = ({num_params},), got {scale.shape}"
        )
    # numpy on concrete values: a jnp comparison under a trace would be traced
    if not isinstance(scale, jax.core.Tracer) and not np.all(np.asarray(scale) > 0):
        raise ValueError("theta_scale must be > 0 everywhere")
    return scale
