"""The front door: ``jaxcal.calibrate(model, data, method=...)``.

One call calibrates any :class:`~jaxcal.model.Model` on any data source with any
method, each unit as its own stream (``lax.scan`` over time, ``vmap`` over units,
jitted), and returns per-row results in the input's row order::

    result = jaxcal.calibrate(model, "data.csv", method="ukf")
    result.theta        # [N, P] numpy, result.theta_names
    result.theta_std    # [N, P] (UKF; None where a method has no uncertainty)
    result.valid        # [N] bool: False where a sample was skipped, result.reason

Methods (peers under the one ``Calibrator(init, step)`` interface):

* ``"ukf"``: the unscented Kalman filter on the model (random-walk parameters);
* ``"ls"``: sliding-window least squares on the model (Levenberg–Marquardt);
* ``"e2e"``: a network ``theta_t = G(w_t, x_t, x_{t-1})`` trained on simulations of
  the model over the parameter box (or pass trained weights as ``e2e=``);
* ``"policy"``: a trained tracking policy, ``run=<run folder>``; an incremental
  (feedback) policy's run with ``anchor=<absolute policy's run folder>`` is gated by
  it where the model misfits the data (:mod:`jaxcal.calibrators.gated`).

A model with hidden states (``Model.from_step``) takes the same call: the UKF
filters the states jointly with the parameters, least squares fits the parameters
and the window's initial state by simulating the model over a sliding window, E2E
reads a window of past samples, a policy carries the model state;
``result.states [N, Z]`` holds the estimated states where a method has them.

Noise: ``noise={output: std}``; when omitted it is estimated from the data as the
residual of a sliding-window least-squares pass (``result.noise_source`` says so).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import jax
import numpy as np

from jaxcal.data.dataset import Dataset, clip_jitter
from jaxcal.data.readers import read_dataset
from jaxcal.model import Model
from jaxcal.problem import Problem

METHODS = ("ukf", "ls", "e2e", "policy")
_READER_OPTIONS = ("rename", "ignore", "nonfinite")


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Per-row results of :func:`calibrate`, in the data's row order.

    Attributes:
        theta: ``[N, P]`` calibrated parameters after each row.
        theta_std: ``[N, P]`` their standard deviation, or ``None``.
        states: ``[N, Z]`` the model's hidden state after each row (the joint UKF's
            filtered state, the window fit's simulated one), or ``None``.
        state_names: ``Z`` names (empty for a static model).
        xhat: ``[N, S]`` the model output that goes with ``theta``.
        valid: ``[N]`` bool; False where the sample was skipped (``reason``).
        reason: ``[N]`` str: ``ok`` or why the sample was skipped.
        theta_names, output_names: column names.
        unit, time: ``[N]`` the rows' unit and time (as read).
        method: the method's name.
        problem: the :class:`~jaxcal.problem.Problem` that was solved.
        notes: what data cleaning did (conditions within 1 % of their range outside
            it, logging jitter, set onto the bound; farther ones are flagged).
    """

    theta: np.ndarray
    theta_std: np.ndarray | None
    states: np.ndarray | None
    state_names: tuple[str, ...]
    xhat: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    theta_names: tuple[str, ...]
    output_names: tuple[str, ...]
    unit: np.ndarray
    time: np.ndarray
    method: str
    problem: Problem
    notes: tuple[str, ...] = ()

    @property
    def num_flagged(self) -> dict:
        """``{reason: rows}`` of the skipped rows."""
        names, counts = np.unique(self.reason[~self.valid], return_counts=True)
        return {str(n): int(c) for n, c in zip(names, counts, strict=True)}

    def to_frame(self):
        """A pandas DataFrame: unit, time, theta (and ``<name>_std``), x-hat
        (``<name>_hat``), valid, reason."""
        import pandas as pd

        cols = {"unit": self.unit, "time": self.time}
        for j, name in enumerate(self.theta_names):
            cols[name] = self.theta[:, j]
            if self.theta_std is not None:
                cols[f"{name}_std"] = self.theta_std[:, j]
        if self.states is not None:
            for j, name in enumerate(self.state_names):
                cols[name] = self.states[:, j]
        for j, name in enumerate(self.output_names):
            cols[f"{name}_hat"] = self.xhat[:, j]
        cols["valid"], cols["reason"] = self.valid, self.reason
        return pd.DataFrame(cols)


def _dtype(model: Model):
    x64 = bool(jax.config.jax_enable_x64)
    if model.x64 and not x64:
        raise ValueError(
            f"model {model.name!r} needs float64 (an iterative solver inside): call "
            "jax.config.update('jax_enable_x64', True) (or "
            "jaxcal.precision.enable_x64()) at the start of your program"
        )
    return np.float64 if x64 else np.float32


def calibrate(
    model: Model | str,
    data,
    method: str = "ukf",
    theta: Sequence[str] | None = None,
    noise: Mapping[str, float] | None = None,
    *,
    outputs: Sequence[str] | None = None,
    seed: int = 0,
    **options,
) -> CalibrationResult:
    """Calibrate ``model`` on ``data`` with ``method`` (see the module docstring).

    Args:
        model: a :class:`~jaxcal.model.Model` or a ``jaxcal.models.load`` spec.
        data: a path (.csv/.parquet/.h5/.txt), a pandas DataFrame or a
            :class:`~jaxcal.data.dataset.Dataset`.
        method: one of :data:`METHODS`.
        theta: calibrated parameter names (default: all the model's).
        noise: output name -> noise standard deviation (default: estimated).
        outputs: outputs to use (default: every model output in the data).
        seed: PRNG seed (E2E training).
        options: method settings — ``q``, ``prior_std`` (UKF), ``window``,
            ``num_iters`` (LS), ``e2e``/``e2e_config``/``e2e_window`` (E2E), ``run``
            (policy); for a model with hidden states ``state_std`` (initial-state
            std: scalar, ``[Z]`` or ``{state: std}``; default 1 % of the state's
            size) and ``state_q`` (UKF process noise on the states per step,
            default 1e-6 of the state's size: the model is trusted);
            and the readers' ``rename``, ``ignore``, ``nonfinite``.

    Returns:
        :class:`CalibrationResult`.

    Raises:
        ValueError: unknown method or option, names that do not match the model,
            bad data (naming file, column and rows).
    """
    from jaxcal.calibrators.methods import build_calibrator, estimate_noise
    from jaxcal.models import load

    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    model = load(model)
    dtype = _dtype(model)
    reader = {k: options.pop(k) for k in _READER_OPTIONS if k in options}
    if method == "policy" and options.get("run"):
        # a trained policy fixes its parameters and outputs: default to the run's
        from jaxcal.training.runs import load_run

        run = options["run"] = load_run(options["run"])
        theta = run.problem.theta_names if theta is None else theta
        outputs = run.problem.output_names if outputs is None else outputs
    data = read_dataset(data, model, **reader).for_model(model, outputs)
    clipped, notes = clip_jitter(data.w, model)
    data = dataclasses.replace(data, w=clipped)
    problem = Problem.build(model, data, theta=theta, noise=noise)
    padded = data.padded(dtype)
    if noise is None and method != "policy":
        state_opts = {k: options[k] for k in ("state_std", "state_q") if k in options}
        problem = estimate_noise(problem, padded, state_opts)
    calibrator, run = build_calibrator(method, problem, padded, seed, options)
    out = run(calibrator, padded)
    return _to_rows(out, padded, data, problem, method, notes)


def _to_rows(out, padded, data: Dataset, problem: Problem, method: str, notes):
    from jaxcal.calibrators.interface import REASONS

    n = data.num_rows
    rows = lambda v, fill=np.nan: padded.to_rows(np.asarray(v), n, fill)  # noqa: E731
    std = None
    if isinstance(out.aux, dict) and "theta_std" in out.aux:
        std = rows(out.aux["theta_std"]).astype(np.float64)
    states = None
    if isinstance(out.aux, dict) and "state" in out.aux:
        states = rows(out.aux["state"]).astype(np.float64)
    valid = rows(out.valid, False).astype(bool)
    reason = np.asarray(REASONS)[rows(out.reason, 0).astype(np.int64)]
    return CalibrationResult(
        theta=rows(out.theta).astype(np.float64),
        theta_std=std,
        states=states,
        state_names=problem.model.state_names,
        xhat=rows(out.xhat).astype(np.float64),
        valid=valid,
        reason=reason,
        theta_names=problem.theta_names,
        output_names=problem.output_names,
        unit=data.unit,
        time=data.time,
        method=method,
        problem=problem,
        notes=tuple(notes),
    )
