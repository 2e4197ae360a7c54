"""A trained tracking policy (CLAC, LAC, SAC) from its run folder
(:mod:`jaxcal.calibrators.methods.policy.trained`); an incremental policy gated by an
absolute policy's run with ``anchor=`` (:mod:`jaxcal.calibrators.methods.policy.gated`).
It reads no measurement noise and is checked against its run's own training range."""

from __future__ import annotations

import dataclasses
from typing import Any

from jaxcal.calibrators.methods.options import learned_built
from jaxcal.calibrators.methods.protocol import Method


@dataclasses.dataclass(frozen=True)
class Policy:
    """A trained tracking policy, ``run=<run folder>``; an incremental (feedback)
    policy's run with ``anchor=<absolute policy's run folder>`` is gated by it where
    the model misfits the data (:mod:`jaxcal.calibrators.methods.policy.gated`)."""

    run: Any = dataclasses.field(default=None, compare=False)
    anchor: Any = dataclasses.field(default=None, compare=False)

    name = "policy"


def build(problem, cfg: Policy, buckets, seed: int = 0):
    """The loaded policy run over the padded groups, checked against its run's
    training range."""
    del buckets, seed
    # lazy: the run's reader (the training job's config and networks) is imported
    # when the method is asked for
    from jaxcal.calibrators.methods.policy.trained import policy_calibrator

    cal, check = policy_calibrator(problem, cfg)
    return learned_built(problem, cal, check)


def prepare(options: dict, theta, outputs):
    """A trained policy fixes its parameters and outputs: the run loaded, its names
    the defaults."""
    if not options.get("run"):
        return options, theta, outputs
    # lazy: imported when the method is asked for (see build)
    from jaxcal.calibrators.methods.policy.trained import load_run

    run = options["run"] = load_run(options["run"])
    theta = run.problem.theta_names if theta is None else theta
    outputs = run.problem.output_names if outputs is None else outputs
    return options, theta, outputs


def _check(problem, cfg: Policy):
    # lazy: imported when the method is asked for (see build)
    from jaxcal.calibrators.methods.policy.trained import run_check

    del problem
    return run_check(cfg.run)


METHOD = Method(
    name="policy",
    config=Policy,
    build=build,
    make=lambda problem, cfg, buckets=None, seed=0: build(problem, cfg, None)[2],
    check=_check,
    label="CLAC",
    reads_noise=False,
    needs_run=True,
    white_std=False,  # its band is its run's, not a white-noise filter's
    chooses_parameters=lambda options: False,  # the run fixes them
)
