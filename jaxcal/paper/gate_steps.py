"""The gated policy (CLAC-gate) in the paper experiment: its fit and its method.

CLAC-gate is :func:`jaxcal.calibrators.methods.policy.gated.make_gated_calibrator` over
the two
trained Dataset #1 policies: the feedback CLAC-inc (incremental actions through F)
and the anchor CLAC (the paper's absolute policy through D). It trains nothing; its
fit step (``fit-ds1-CLAC-gate``) uses the validation units only (never test labels):

1. the anchor over the validation units → its error band (split-conformal, the
   bands of :mod:`jaxcal.calibrators.uncertainty.conformal`), which sets the gate's
   threshold;
2. the gated policy over the same units → its own band (``aux["theta_std"]``, the
   coverage the report scores);

and stores both with the feedback's sensitivity under the suite's model folder
(``clac-gate.json``), like the E2E weights. Its evaluation and latency steps are the
other methods' (``eval-ds1-CLAC-gate-*``, ``latency-ds1-CLAC-gate``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator
from jaxcal.calibrators.methods.policy.gated import (
    DEFAULT_WINDOW,
    Z90,
    feedback_sensitivity,
    gate_threshold,
    make_gated_calibrator,
)
from jaxcal.calibrators.methods.policy.loading import load_run, needs_x64
from jaxcal.calibrators.uncertainty.conformal import (
    band_coverage,
    band_from_json,
    band_to_json,
    fit_band,
)
from jaxcal.paper.compare import evaluate_method
from jaxcal.paper.methods import Method, make_method
from jaxcal.runs.atomic import write_atomic

NAME, FEEDBACK, ANCHOR = "CLAC-gate", "CLAC-inc", "CLAC"
GATE_FILE = "clac-gate.json"


def gate_path(suite) -> Path:
    return Path(suite.model_dir) / GATE_FILE


def gated_method(suite, gate: dict | None = None) -> Method:
    """CLAC-gate from the suite's CLAC and CLAC-inc runs and the stored fit.

    Args:
        suite: a :class:`~jaxcal.paper.suite.Suite` with both runs.
        gate: the fit (``None``: read ``clac-gate.json``; without an own band the
            method reports no std, as during the fit).

    Raises:
        FileNotFoundError: no stored fit (run the ``fit-ds1-CLAC-gate`` step).
    """
    if gate is None:
        path = gate_path(suite)
        if not path.is_file():
            raise FileNotFoundError(
                f"{path} missing: CLAC-gate needs its fit step (fit-ds1-CLAC-gate) "
                "before it is evaluated"
            )
        gate = json.loads(path.read_text())
    feedback, anchor = suite.method(FEEDBACK), suite.method(ANCHOR)
    source = str(gate_path(suite))
    anchor_band = band_from_json(gate["anchor_band"], source, jnp.float64)
    band = band_from_json(gate["band"], source, jnp.float64) if gate["band"] else None
    x_std = jnp.asarray(gate["x_std"], jnp.float64)
    sens = jnp.asarray(gate["sensitivity"], jnp.float64)
    window = int(gate["window"])

    def gated(fb: Calibrator, an: Calibrator) -> Calibrator:
        return make_gated_calibrator(
            fb, an, x_std=x_std, sensitivity=sens, anchor_band=anchor_band,
            window=window, band=band,
        )  # fmt: skip

    def build(bias, noise_sigma):
        return gated(feedback.build(bias, noise_sigma), anchor.build(bias, noise_sigma))

    info = {"feedback": feedback.info, "anchor": anchor.info, "window": window}
    return make_method(
        NAME, build, jnp.float64, info, check=feedback.check,
        deploy_fn=lambda: gated(feedback.deploy(), anchor.deploy()),
        warm=feedback.warm,
    )  # fmt: skip


def fit_step(suite, *, window: int = DEFAULT_WINDOW) -> dict:
    """Fit CLAC-gate's bands on the validation units and store them.

    Returns:
        ``{"method", "val_units", "anchor_val_theta_rmse", "val_theta_rmse",
        "val_coverage90", "sensitivity", "threshold_median", "window",
        "fit_seconds", "gate"}``.
    """
    tic = time.perf_counter()
    val = suite.data.val
    with jax.enable_x64(needs_x64(suite.runs[FEEDBACK])):
        params = load_run(suite.runs[FEEDBACK]).params
    with jax.enable_x64(False):  # the anchor as it is scored everywhere (float32)
        anchor_run = evaluate_method(suite.method(ANCHOR), val, suite.problem)
    anchor_band = fit_band(anchor_run.theta, val.theta, val.mask)
    gate = {
        "window": window,
        "sensitivity": feedback_sensitivity(params).tolist(),
        "x_std": np.asarray(params.x_std, np.float64).tolist(),
        "anchor_band": band_to_json(anchor_band),
        "band": None,
    }
    with jax.enable_x64(True):  # the feedback runs on F in float64
        gated = evaluate_method(gated_method(suite, gate), val, suite.problem)
    band = fit_band(gated.theta, val.theta, val.mask)
    gate["band"] = band_to_json(band)
    path = gate_path(suite)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(gate, indent=2) + "\n")
    suite.forget(NAME)  # rebuilt from the stored fit, with its band
    coverage, _ = band_coverage(band, gated.theta, val.theta, val.mask)
    tau = gate_threshold(
        jnp.asarray(gate["sensitivity"]), Z90 * jnp.asarray(anchor_band.std)
    )
    return {
        "method": NAME,
        "val_units": val.unit_ids.tolist(),
        "anchor_val_theta_rmse": anchor_run.scores["theta_rmse"],
        "val_theta_rmse": gated.scores["theta_rmse"],
        "val_coverage90": coverage,
        "sensitivity": gate["sensitivity"],
        "threshold_median": float(np.median(tau)),
        "window": window,
        "fit_seconds": time.perf_counter() - tic,
        "gate": str(path),
    }
