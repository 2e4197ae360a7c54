"""How a training run scores its policy: an agent state as the deployable policy,
run over units and scored.

:func:`make_policy_scoring` closes over one run (its environment, components,
normalised problem and range check) and returns :class:`PolicyScoring`: the
deployable :class:`~jaxcal.calibrators.methods.policy.calibrator.PolicyParams` of an
agent state (its
Polyak-averaged target actor or its online one), the deployment calibrator's run over
units (:mod:`jaxcal.calibrators.methods.policy.calibrator`, ``lax.scan`` vmapped over
units, in the run's dtype), the scores of such a run
(:func:`jaxcal.training.scoring.trajectories.score_units`),
the validation scores the host loop logs and selects by, and the test units' theta
RMSE it may report (time to target; selection never reads it).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

from jaxcal.calibrators.methods.policy.calibrator import (
    PolicyParams,
    filter_settings,
    policy_params_from_env,
    range_check,
)
from jaxcal.data.padded import Padded
from jaxcal.envs.tracking import EnvParams
from jaxcal.problem import Problem
from jaxcal.training.config import TrainConfig
from jaxcal.training.data.calibration import CalibrationData
from jaxcal.training.scoring.trajectories import score_units, theta_rmse
from jaxcal.training.stages.uncertainty import scored_mask


class PolicyScoring(NamedTuple):
    """The policy functions of one run.

    Attributes:
        deployable: ``(agent_state, which=budget.policy) -> PolicyParams``
            (``which``: ``"target"`` or ``"online"``).
        run: ``(units, params, band=None) -> CalOutput``, the deployed policy over
            the units (with ``band``: its ``aux["theta_std"]``).
        score: ``(units, params, out=None) -> dict`` of
            :func:`~jaxcal.training.scoring.trajectories.score_units` (``out``: a run
            already made).
        val_scorer: ``agent_state -> dict``: the validation units' theta and
            tracking RMSE, and with ``budget.select=sim_theta`` the theta RMSE on
            simulated units (``sim_theta_rmse``); ``None`` with neither.
        sim_theta: ``(units, params) -> (pooled, per parameter)`` theta RMSE in box
            widths on labelled units (the selection's score on simulated ones).
        last_val_out: ``() -> CalOutput | None``, the last ``val_scorer`` call's run
            over the validation units: the band is fitted on the kept chunk's run,
            made once when it was scored, not run again.
    """

    deployable: Callable[..., PolicyParams]
    run: Callable[[Padded, PolicyParams], Any]
    score: Callable[..., dict]
    val_scorer: Callable[[Any], dict] | None
    sim_theta: Callable[..., tuple]
    last_val_out: Callable[[], Any]


def make_policy_scoring(
    cfg: TrainConfig,
    data: CalibrationData,
    problem: Problem,
    parts,
    train_params: EnvParams,
    max_increment: float | None,
    dtype,
    select_units: Padded | None,
) -> PolicyScoring:
    """:class:`PolicyScoring` of a run on ``problem`` (normalised as ``train_params``)
    with its components ``parts`` (``run_units``); ``select_units``: the simulated
    units of ``budget.select=sim_theta``, else ``None``."""
    check = range_check(problem)  # samples far outside the training range: flagged
    start = problem.theta_prior if cfg.env.start == "prior" else None

    def run(units: Padded, params: PolicyParams, band=None):
        w, x = units.w.astype(dtype), units.x.astype(dtype)
        return parts.run_units(params, w, x, units.mask, check, band)

    def score(units: Padded, params: PolicyParams, out=None) -> dict:
        out = run(units, params) if out is None else out
        return score_units(
            out.theta,
            out.xhat,
            units.theta,
            units.x,
            units.mask,
            problem.norm.x_std,
            problem.output_names,
            problem.theta_names,
            reason=out.reason,
        )

    def deployable(agent_state, which: str = cfg.budget.policy) -> PolicyParams:
        actor = agent_state.actor.params
        if which == "target":
            actor = getattr(agent_state, "target_actor_params", actor)
        return policy_params_from_env(
            train_params, actor, max_increment=max_increment, theta_start=start,
            **filter_settings(parts.env.config),
        )  # fmt: skip

    def sim_theta(units: Padded, params: PolicyParams):
        """``(pooled, per parameter)`` theta RMSE in box widths on labelled
        (simulated) ``units``: what ``budget.select=sim_theta`` selects by."""
        out = run(units, params)
        width = problem.theta_high - problem.theta_low
        return theta_rmse(
            out.theta / width, units.theta / width, scored_mask(units, out)
        )

    last = {"val_out": None}

    def val_scorer(agent_state) -> dict:
        params = deployable(agent_state)
        scores = {}
        if data.val is not None:
            last["val_out"] = run(data.val, params)
            scores = score(data.val, params, last["val_out"])
            keys = ("theta_rmse", "tracking_rmse_norm")
            scores = {k: scores[k] for k in keys if scores[k] is not None}
        if select_units is not None:
            scores["sim_theta_rmse"], each = sim_theta(select_units, params)
            # per parameter too (logged, not selected on): which one a chunk moves
            for name, value in zip(problem.theta_names, each, strict=True):
                scores[f"sim_theta_rmse_{name}"] = float(value)
        return scores

    scored = data.val is not None or select_units is not None
    return PolicyScoring(
        deployable, run, score, val_scorer if scored else None, sim_theta,
        lambda: last["val_out"],
    )  # fmt: skip
