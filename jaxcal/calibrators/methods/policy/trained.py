"""A trained policy as a method: the loaded run, its calibrator and its sample check.

``jaxcal.calibrate(model, data, method="policy", run=<folder>)`` and the method
table's policy (:mod:`jaxcal.calibrators.methods`) calibrate with a run of the
training job. What they need of it is here: :class:`LoadedRun` (the record of a
loaded run), :func:`load_calibrator` (its policy as a ``Calibrator(init, step)``,
gated by an anchor run where asked), :func:`run_check` (its training range as the
sample check) and :func:`check_run_model` (the model given is the run's own,
:mod:`jaxcal.calibrators.methods.policy.run_model`).

The run folder is read by :mod:`jaxcal.calibrators.methods.policy.loading`
(:func:`load_run`, with the training job's config and components, which sit at this
layer). Users import all of this from :mod:`jaxcal.deploy`.
"""

from __future__ import annotations

import os

from jaxcal.calibrators.interface import Calibrator, SampleCheck
from jaxcal.calibrators.methods.policy.calibrator import (
    make_policy_calibrator,
    range_check,
)
from jaxcal.calibrators.methods.policy.gated import (
    feedback_sensitivity,
    make_gated_calibrator,
)
from jaxcal.calibrators.methods.policy.loading import LoadedRun, load_run
from jaxcal.calibrators.methods.policy.run_model import check_run_model  # noqa: F401 (re-exported)
from jaxcal.calibrators.programs import compiled


def run_check(run: LoadedRun) -> SampleCheck | None:
    """The run's valid input box (training range + margin; ``None``: finiteness).

    Pass it as ``check=`` to ``run_calibrator`` / ``run_fleet`` / the fleet paths.
    """
    return range_check(run.problem)


def load_calibrator(
    run_dir: str | os.PathLike | LoadedRun,
    anchor: str | os.PathLike | LoadedRun | None = None,
    *,
    warm_start: bool = False,
) -> Calibrator:
    """The run's policy as a ``Calibrator(init, step)`` (pure functions, not jitted).

    Use it like any other method: ``jax.jit(run_fleet, static_argnums=0)(cal, w, x,
    m)``, with ``check=run_check(run)`` to flag samples outside the training range.

    Args:
        run_dir: the run (folder or loaded).
        anchor: an absolute policy's run with its band (``uncertainty.json``): the
            run, an incremental policy, is then gated by it where the model misfits
            the data (:mod:`jaxcal.calibrators.methods.policy.gated`).
        warm_start: for one stream, one sample per call (its first state made
            before any row); keep the default for ``run_fleet`` over many units.
            The model's solver is warm-started from the previous sample where it
            can be, either way
            (:func:`~jaxcal.calibrators.methods.policy.calibrator.make_policy_calibrator`).

    Raises:
        ValueError: the anchor has no band, its names differ from the run's, or the
            run is not an incremental policy.
    """
    run = load_run(run_dir)
    # run_fleet gives init the first ok row; a stream (warm_start) makes its first
    # state before any row and starts the model's state at its first sample
    cal = make_policy_calibrator(
        run.actor, run.dynamics, run.params, run.band, warm_start=True,
        start_at_first_sample=warm_start,
    )  # fmt: skip
    if anchor is None:
        return cal
    anchor = load_run(anchor)
    check_anchor(run, anchor)
    anchor_cal = make_policy_calibrator(
        anchor.actor, anchor.dynamics, anchor.params, anchor.band,
        warm_start=True, start_at_first_sample=warm_start,
    )  # fmt: skip
    return make_gated_calibrator(
        cal,
        anchor_cal,
        x_std=run.params.x_std,
        sensitivity=feedback_sensitivity(run.params),
        anchor_band=anchor.band,
    )


def check_anchor(run: LoadedRun, anchor: LoadedRun) -> None:
    """An anchor must calibrate the same problem and carry its band.

    Raises:
        ValueError: naming the anchor's folder and what differs.
    """
    if anchor.band is None:
        raise ValueError(
            f"anchor run {anchor.run_dir} has no uncertainty.json (the error band "
            "the training job fits at its end): the gate's threshold is the "
            "anchor's 90 % half-width"
        )
    for field in ("theta_names", "output_names"):
        if tuple(getattr(anchor.problem, field)) != tuple(getattr(run.problem, field)):
            raise ValueError(
                f"anchor run {anchor.run_dir} has {field} "
                f"{list(getattr(anchor.problem, field))}, the run {run.run_dir} "
                f"{list(getattr(run.problem, field))}: both must calibrate one problem"
            )


def policy_calibrator(problem, cfg) -> tuple[Calibrator, SampleCheck | None]:
    """A trained policy from ``run=<folder>`` and its sample check (the run's own
    training range, not the range of the data being calibrated); its names must
    match the problem, and the problem's model must be the run's own (by names and
    by outputs at probe points, :mod:`jaxcal.calibrators.methods.policy.run_model`).
    With ``anchor=<folder>`` (an absolute policy's run with its
    band) the run, an incremental policy, is gated by it (:mod:`jaxcal.calibrators.
    gated`): the feedback while the model fits the data, the anchor where not."""
    run_dir, anchor_dir = cfg.run, cfg.anchor
    if not run_dir:
        raise ValueError("method='policy' needs run=<trained run folder>")
    run = load_run(run_dir)
    _check_run(problem, run)
    check_run_model(run, problem.model)  # the policy runs with the run's own model
    anchor = None
    # the feedback gated by an absolute policy (calibrators.methods.policy.gated)
    if anchor_dir:
        anchor = load_run(anchor_dir)
        _check_run(problem, anchor)
        check_run_model(anchor, problem.model)
    # one calibrator per (run, checkpoint, anchor) in a process: a repeat call
    # reuses its compiled program (the policy's weights are the program's constants)
    key = (
        str(run.run_dir), run.step,
        None if anchor is None else (str(anchor.run_dir), anchor.step),
    )  # fmt: skip
    cal = compiled.cached_value(("policy", key), lambda: load_calibrator(run, anchor))
    return cal, run_check(run)


def _check_run(problem, run) -> None:
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
