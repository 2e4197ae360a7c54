"""A feedback policy gated by the model's fit, with an absolute policy as its anchor.

The two policy formulations fail in opposite places (``results/train/feedback.md``):

* the *feedback* (incremental actions through F, :mod:`jaxcal.envs.increment`) drives
  the prediction error to zero: as precise as the exact-model UKF on a right model,
  but on a biased one (F x 1.02) it follows the bias to the box edge, like the UKF;
* the *absolute* policy (theta = pi(x-hat_{t-1}, x_t, w_t) through D) barely uses the
  model at deployment: 30x less precise, but robust to model error.

The gate chooses per sample with the one fact that separates the cases, which the
feedback already computes: whether the model can explain the data. Its prediction
error r_t = RMS_s((x_t - F(w_t, theta_{t-1})) / sigma_x) collapses to the solver's
floor (1e-12) once the feedback has converged on a right model, and stays at the size
of the model error otherwise. The threshold is what the anchor's own uncertainty could
explain: a theta off by the anchor's 90 % half-width h_p moves the normalised outputs by
about J_p h_p, J_p the feedback's RMS sensitivity (``increment_step_ref``), so

    open_t  =  min(r_t, ..., r_{t-k+1})  <=  tau_t = sqrt(sum_p (J_p h_p(t))^2)
    theta_t =  theta_feedback_t if open_t else theta_anchor_t

i.e. the feedback is trusted while, within the last ``window`` samples, the model fit
the data better than the anchor is known to; a single-sample spike (a step change of
theta, the first samples of a stream) does not close the gate, a persistent misfit
(model bias, model noise, heavy sensor noise) does. Both policies run on every sample
(each keeps its own state), so the switch is immediate in either direction. This is a
model-validity monitor in the sense of residual-based fault detection (Isermann 2006,
ch. 10): a residual that no admissible parameter change explains flags the model.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator, CalStepOutput
from jaxcal.calibrators.uncertainty.conformal import ThetaBand, band_std, z_value
from jaxcal.typedefs import Array, PRNGKey

DEFAULT_WINDOW = 2  # samples a misfit must last before the anchor takes over
Z90 = z_value(0.9)  # the anchor's 90 % half-width is Z90 std


class GateState(NamedTuple):
    """The two policies' states and the gate's memory.

    Attributes:
        feedback, anchor: each policy's own calibrator state.
        recent: ``[window]`` the last prediction-error RMS values, newest first
            (the largest float before the stream has that many samples: the
            sample guard flags a non-finite state).
        count: ``[]`` int32 samples seen (indexes the bands).
    """

    feedback: Any
    anchor: Any
    recent: Array
    count: Array


def gate_state(feedback_state, anchor_state, window: int, dtype) -> GateState:
    """The gate's state before its first sample, around the two policies' states
    (a guarded stream builds them without an ``init`` sample)."""
    return GateState(
        feedback=feedback_state,
        anchor=anchor_state,
        recent=jnp.full((window,), jnp.finfo(dtype).max, dtype),
        count=jnp.zeros((), jnp.int32),
    )


def feedback_sensitivity(params) -> np.ndarray:
    """J_p of an incremental policy's params, inverting ``n_ref = 0.5 J M``.

    ``step_ref`` was set at training (:func:`jaxcal.envs.increment.increment_step_ref`)
    from finite differences of the model over training rows; M is the largest step
    (``max_increment`` times the box width).

    Raises:
        ValueError: ``params`` are not an incremental policy's.
    """
    step_ref = getattr(params, "step_ref", None)
    if step_ref is None:
        raise ValueError(
            "the gated calibrator's feedback must be an incremental policy "
            "(env.action=increment); its params have no step_ref"
        )
    width = np.asarray(params.theta_high, np.float64) - np.asarray(
        params.theta_low, np.float64
    )
    return 2.0 * np.asarray(step_ref, np.float64) / (params.max_increment * width)


def gate_threshold(sensitivity, halfwidth) -> Array:
    """tau = sqrt(sum_p (J_p h_p)^2): the normalised output RMS a theta error of
    ``halfwidth`` ``[..., P]`` produces (sensitivity ``[P]``)."""
    return jnp.sqrt(jnp.sum(jnp.square(sensitivity * halfwidth), axis=-1))


def make_gated_calibrator(
    feedback: Calibrator,
    anchor: Calibrator,
    *,
    x_std,
    sensitivity,
    anchor_band: ThetaBand,
    window: int = DEFAULT_WINDOW,
    band: ThetaBand | None = None,
) -> Calibrator:
    """The gated policy (module docstring) as ``Calibrator(init, step)``.

    Args:
        feedback: the incremental policy's calibrator (its ``xhat`` is the prediction
            F(w_t, theta_{t-1}) the gate tests).
        anchor: the absolute policy's calibrator.
        x_std: ``[S]`` the outputs' normalisation (the feedback's ``x_std``).
        sensitivity: ``[P]`` the feedback's J (:func:`feedback_sensitivity`).
        anchor_band: the anchor's calibrated error band (its 90 % half-width sets
            the threshold at each sample since the stream's start).
        window: samples of misfit before the anchor takes over (>= 1).
        band: the gated policy's error band while the gate is open
            (``aux["theta_std"]``, fitted on validation units); a closed gate
            reports the anchor's band. ``None`` (or a relative band, which only
            the feedback calibrator can scale): the std of the branch in use when
            both report one (each policy's own band), else no std.

    Returns:
        A calibrator whose ``xhat`` is the feedback's model prediction and whose
        ``aux`` has ``gate_open`` ``[]`` bool, ``residual`` ``[]`` (r_t) and, with a
        band, ``theta_std`` ``[P]``.

    Raises:
        ValueError: ``window`` < 1.
    """
    if int(window) < 1:
        raise ValueError(f"window must be an integer >= 1, got {window!r}")
    window = int(window)
    x_std = jnp.asarray(x_std)
    sens = jnp.asarray(sensitivity)

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> GateState:
        fb, an = feedback.init(key, w0, x0), anchor.init(key, w0, x0)
        return gate_state(fb, an, window, x0.dtype)

    def step(state: GateState, w: Array, x: Array) -> tuple[GateState, CalStepOutput]:
        fb_state, fb = feedback.step(state.feedback, w, x)
        an_state, an = anchor.step(state.anchor, w, x)
        resid = (x - fb.xhat.astype(x.dtype)) / x_std.astype(x.dtype)
        r = jnp.sqrt(jnp.mean(jnp.square(resid)))
        # a failed prediction is a misfit (finite: the guard checks the state)
        r = jnp.where(jnp.isfinite(r), r, jnp.finfo(x.dtype).max)
        recent = jnp.concatenate([r[None], state.recent[:-1]])
        halfwidth = Z90 * band_std(anchor_band, state.count)
        tau = gate_threshold(sens.astype(x.dtype), halfwidth.astype(x.dtype))
        is_open = jnp.min(recent) <= tau
        theta = jnp.where(is_open, fb.theta, an.theta.astype(fb.theta.dtype))
        aux = {"gate_open": is_open, "residual": r}
        if band is not None and not band.relative:  # closed: the anchor's band
            std = jnp.where(is_open, band_std(band, state.count), halfwidth / Z90)
            aux["theta_std"] = std.astype(theta.dtype)
        elif _std(fb) is not None and _std(an) is not None:  # each branch's own band
            # (a relative band scales what the feedback's own filter predicts: the
            # feedback calibrator reports it, band_std alone cannot)
            aux["theta_std"] = jnp.where(
                is_open, _std(fb), _std(an).astype(theta.dtype)
            )
        new_state = GateState(fb_state, an_state, recent, state.count + 1)
        return new_state, CalStepOutput(theta=theta, xhat=fb.xhat, aux=aux)

    return Calibrator(init, step)


def _std(out: CalStepOutput):
    return out.aux.get("theta_std") if isinstance(out.aux, dict) else None
