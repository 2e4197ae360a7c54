"""Real-time calibration with a trained run: the deployment API.

A run folder written by ``python -m jaxcal.train`` holds everything a policy needs:
``config.json`` (architecture, dynamics), ``data.json`` (the model spec and the
problem: names, units, box, normalisation, training range) and ``policy/`` (actor
weights, surrogate weights, normalisation and action box, saved at every
checkpoint). No data file and no training code path is needed to deploy, for the
turbofan or any other model::

    from jaxcal.deploy import StreamingCalibrator

    cal = StreamingCalibrator("runs/cmapss-clac-physics-inc-s0")
    for w_t, x_t in stream:                  # w_t [W]: cal.conditions, x_t [S]
        theta_t = cal.step(w_t, x_t)         # [P] numpy, one jitted call
    theta, xhat = cal.run(w, x, mask)        # batch: [U, T, W], [U, T, S], [U, T]

    # a feedback run gated by an absolute run where the model misfits the data
    gated = StreamingCalibrator(feedback_run, anchor=absolute_run)

Guarded samples: a sample with NaN / Inf in ``w`` or ``x``, or far outside the run's
training range (:func:`jaxcal.calibrators.methods.policy.calibrator.range_check`), is
*skipped*: the carried state is left exactly as it was, ``step`` returns the last valid
theta (before any valid sample the theta the stream starts from, inside the box) and the
flag is readable (``cal.last_valid``, ``cal.last_reason``,
:meth:`StreamingCalibrator.step_info`; ``run(..., return_flags=True)``). The stream then
continues as if the sample had never arrived. Runs trained before the range was stored
check finiteness only.

Semantics (:mod:`jaxcal.calibrators.methods.policy.calibrator`): the calibrator carries
the model output x-hat internally; each sample gives theta_t =
box(pi*(norm(x-hat_{t-1}), norm(x_t), norm(w_t))) and x-hat_t = D(w_t, x-hat_{t-1},
theta_t) (or F with ``dynamics=physics``). A model with memory carries its hidden state
z as well, z_0 = the state after the first sample with the prior theta
(:mod:`jaxcal.envs.memory`). :func:`load_calibrator` returns the same method as a
:class:`~jaxcal.calibrators.interface.Calibrator`, so it runs beside the other methods
through ``run_calibrator`` / ``run_fleet``; ``jaxcal.calibrate(model, data,
method="policy", run=<folder>)`` does the same on a data file.

A run folder is self-contained: ``data.json`` records its model, and a model file
(``model=file.py:attr``) is copied into ``model/`` with its sha256; loading the run
runs that copy (an edited copy is refused), never a path outside the folder, so a
run loads after its model file moved and does not follow later edits of it
(:mod:`jaxcal.training.model_source`). Loading a run folder runs its model's code,
as loading a pickle does: load only run folders you trust. A run of the older
layout, whose model is a file outside it, is refused; :func:`adopt_model_file`
copies a file you trust into it.

For the lowest cost a sample, call :func:`synchronous_dispatch` at the start of the
program, before any JAX computation (or set ``JAX_CPU_ENABLE_ASYNC_DISPATCH=false``):
JAX then runs each step on the calling thread instead of handing it to a thread pool,
about half the cost of a small model's step; the results are the same bits.

The package holds deployment: :mod:`jaxcal.deploy.streaming` runs a run sample by
sample; reading a run folder (:func:`load_run`), the record of a loaded run and its
calibrator are the policy method's (:mod:`jaxcal.calibrators.methods.policy.loading`,
:mod:`~jaxcal.calibrators.methods.policy.trained`), re-exported here. A run whose model
needs float64 with ``dynamics=physics`` needs x64 enabled first
(``jaxcal.precision.enable_x64()``).
"""

from jaxcal.calibrators.methods.policy.trained import (
    LoadedRun,
    load_calibrator,
    load_run,
    run_check,
)
from jaxcal.calibrators.programs.packed import synchronous_dispatch
from jaxcal.deploy.streaming import StepInfo, StreamingCalibrator
from jaxcal.training.model_source import adopt_model_file

__all__ = [
    "LoadedRun",
    "StepInfo",
    "StreamingCalibrator",
    "adopt_model_file",
    "load_calibrator",
    "load_run",
    "run_check",
    "synchronous_dispatch",
]
