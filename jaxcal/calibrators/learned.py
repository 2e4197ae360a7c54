"""The learned methods (E2E, a trained policy) ready to run for the front door.

The E2E network learns the inverse of the model from simulations over the box at the
data's own operating conditions (:mod:`jaxcal.calibrators.methods.e2e.simulated`), or
takes given
weights; a trained policy is loaded from its run folder, gated by an absolute
policy's run with ``anchor=`` (:mod:`jaxcal.calibrators.methods.policy.gated`). Either
is a ``Calibrator`` built outside the compiled programs, run by one jitted fleet scan
(:func:`make_runner`) with a sample check: the data's range for E2E, the run's own
training range for a policy.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator, SampleCheck, run_fleet
from jaxcal.calibrators.methods.options import Built
from jaxcal.calibrators.programs import compiled
from jaxcal.data.buckets import Buckets
from jaxcal.data.padded import Padded
from jaxcal.problem import Problem

_FLEET = jax.jit(run_fleet, static_argnums=0)  # one dispatch cache per process


def make_runner(check: SampleCheck | None):
    """``run(calibrator, padded, skip=None) -> CalOutput``: the fleet scan of a
    calibrator built outside the compiled programs (E2E, a policy), jitted; the same
    calibrator object again runs without tracing again."""
    fleet = _FLEET

    def run(calibrator: Calibrator, padded: Padded, skip=None):
        mask = padded.mask if skip is None else padded.mask & ~np.asarray(skip)
        return fleet(
            calibrator, jnp.asarray(padded.w), jnp.asarray(padded.x),
            jnp.asarray(mask), check=check,
        )  # fmt: skip

    return run


def learned_built(problem: Problem, cal: Calibrator, check) -> Built:
    """:class:`Built` of a learned calibrator: the jitted fleet scan with ``check``,
    and a uniform's std over the box before a stream's first sample."""
    runner = make_runner(check)
    uniform = problem.theta_half_width / np.sqrt(3.0)
    return Built(lambda padded, skip=None: runner(cal, padded, skip), uniform, cal)


def e2e_calibrator(problem: Problem, buckets: Buckets, seed: int, cfg) -> Calibrator:
    """A given E2E network, or one trained on simulations of the model (E2E-sim)."""
    from jaxcal.calibrators.methods.e2e.network import E2EConfig, make_e2e_calibrator
    from jaxcal.calibrators.methods.e2e.simulated import fit_e2e_sim, held_out_band
    from jaxcal.nets.mlp import RegressorConfig

    params = cfg.e2e
    measure = problem.measure() if not problem.model.is_stateful else None
    window = cfg.e2e_window
    window = int((16 if measure is None else 0) if window is None else window)
    if params is None:
        fit = cfg.e2e_config or E2EConfig(
            hidden_sizes=(64, 64),
            fit=RegressorConfig(
                learning_rate=1e-3, batch_size=256, num_epochs=60,
                validation_fraction=0.1, patience=10,
            ),
        )  # fmt: skip
        copies = int(cfg.e2e_copies)
        params = fit_e2e_sim(problem, buckets, fit, seed, copies, window)[0]
    # a std only where held-out simulations say what G's error is (not for given
    # weights); every estimate projected into the declared box
    band = held_out_band(problem, buckets, params, seed) if cfg.e2e is None else None
    box = (problem.theta_low, problem.theta_high)
    if measure is not None:
        return make_e2e_calibrator(params, measure, box=box, band=band)
    return make_e2e_calibrator(
        params, transition=problem.transition(),
        theta0=jnp.asarray(problem.theta_prior, buckets.dtype), box=box, band=band,
    )  # fmt: skip


def policy_calibrator(problem: Problem, cfg) -> tuple[Calibrator, SampleCheck | None]:
    """A trained policy from ``run=<folder>`` and its sample check (the run's own
    training range, not the range of the data being calibrated); its names must
    match the problem, and the problem's model must be the run's own (by names and
    by outputs at probe points, :mod:`jaxcal.calibrators.methods.policy.run_model`).
    With ``anchor=<folder>`` (an absolute policy's run with its
    band) the run, an incremental policy, is gated by it (:mod:`jaxcal.calibrators.
    gated`): the feedback while the model fits the data, the anchor where not."""
    # A run folder is read through jaxcal.runs.read_run (the deploy layer's loader,
    # registered by the package root); imported here, when the method is asked for,
    # not at import time.
    from jaxcal.calibrators.methods.policy.trained import (
        LoadedRun,
        check_run_model,
        load_calibrator,
        load_run,
        run_check,
    )

    run_dir, anchor_dir = cfg.run, cfg.anchor
    if not run_dir:
        raise ValueError("method='policy' needs run=<trained run folder>")
    run = run_dir if isinstance(run_dir, LoadedRun) else load_run(run_dir)
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
