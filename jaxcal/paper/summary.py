"""The issue's headline numbers (issue 15): is the RL calibrator good enough yet?

:func:`issue_summary` reads six numbers from the step results of
``experiments/paper.py`` — the best policy's theta RMSE against the UKF's on clean
Dataset #1 and under model bias x 1.02, both methods' 90 % interval coverage, the
policy's training time to its target and its single-stream deployment speed-up over
the UKF — and :func:`summary_goals` sets them against the issue's goals. Both go to
``results.json`` (keys ``"summary"``, ``"summary_goals"``, ``"summary_policy"``,
``"summary_details"``) and :func:`summary_section` to the top of ``REPORT.md``. The
UKF's coverage is that of its std rescaled on the validation units when the
``calib-ds1-UKF`` step ran (:mod:`jaxcal.paper.std_steps`; the raw one is kept in
``summary_details``), else its raw std's. A number whose inputs are missing
is ``None`` (JSON null), never a guess; nothing here computes a result beyond a ratio.

The "best policy" is the issue's configuration, CLAC-gate (the feedback CLAC-inc,
incremental actions through F, with the paper's CLAC taking over where F misfits the
data: :mod:`jaxcal.calibrators.methods.policy.gated`), when its clean Dataset #1
evaluation exists,
else CLAC-inc, else the paper's CLAC: a run without them (``skip=CLAC-inc``) still gets
a summary. CLAC-gate trains nothing of its own: its time to target is its feedback's
(the default ``make train``); the anchor's training is the paper's CLAC.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from jaxcal.paper.tables import NAMES, PAPER, Results, ratio, table

BEST_POLICIES = ("CLAC-gate", "CLAC-inc", "CLAC")  # the first one evaluated
# the training whose time to target a policy reports: CLAC-gate's feedback is CLAC-inc
# (its anchor is the paper's CLAC, trained beside it: its time is in the timing table)
TRAINED_AS = {"CLAC-gate": "CLAC-inc"}

# The issue's goals: key -> (lowest, highest) acceptable value (None: unbounded).
GOALS = {
    "ds1_clac_over_ukf": (None, 3.0),
    "ds1_bias_clac_over_ukf": (None, 0.2),
    "ds1_policy_coverage90": (0.85, 0.95),
    "ds1_ukf_coverage90": (0.85, 0.95),
    "train_to_target_s": (None, 600.0),
    "ds1_policy_deploy_speedup_vs_ukf": (5.0, None),
}
LABELS = {
    "ds1_clac_over_ukf": "theta RMSE policy / UKF, clean Dataset #1",
    "ds1_bias_clac_over_ukf": "theta RMSE policy / UKF, model bias F x 1.02",
    "ds1_policy_coverage90": "policy 90 % interval coverage, Dataset #1",
    "ds1_ukf_coverage90": "UKF 90 % interval coverage, Dataset #1",
    "train_to_target_s": "policy training time to target (s)",
    "ds1_policy_deploy_speedup_vs_ukf": "deployment speed-up over the UKF "
    "(single-stream s/sample)",
}
# The paper's own figures for the same quantities (Tian et al. report no intervals
# and the total training time, not a time to a target).
PAPER_SUMMARY = {
    "ds1_clac_over_ukf": ratio(PAPER["inference"]["ds1"]["CLAC"],
                               PAPER["inference"]["ds1"]["UKF"]),
    "ds1_bias_clac_over_ukf": ratio(PAPER["bias"]["CLAC"], PAPER["bias"]["UKF"]),
    "ds1_policy_coverage90": None,
    "ds1_ukf_coverage90": None,
    "train_to_target_s": PAPER["train_s"]["CLAC"],
    "ds1_policy_deploy_speedup_vs_ukf": ratio(PAPER["deploy_s"]["UKF"],
                                              PAPER["deploy_s"]["CLAC"]),
}  # fmt: skip


def best_policy(r: Results) -> str:
    """The policy the summary is about: the first of :data:`BEST_POLICIES` with a
    clean Dataset #1 evaluation (CLAC when none has one)."""
    return next((p for p in BEST_POLICIES if r.eval("ds1", p) is not None), "CLAC")


def _number(value) -> float | None:
    """``value`` as a finite float, else None (a string or NaN is not a number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def time_to_target(train: dict | None) -> float | None:
    """``time_to_target_s`` of a training step, or of its run's ``final.json`` when
    the step predates the copy (None when neither records it)."""
    if train is None:
        return None
    value = train.get("time_to_target_s")
    if value is None and train.get("run_dir"):
        final = Path(train["run_dir"]) / "final.json"
        if final.is_file():
            value = json.loads(final.read_text()).get("time_to_target_s")
    return _number(value)


def _latency(r: Results, method: str) -> float | None:
    step = r.steps.get(f"latency-ds1-{method}")
    return None if step is None else _number(step.get("median_s"))


# the step of :mod:`jaxcal.paper.std_steps`: the UKF's std scaled on validation units
UKF_CALIB_STEP = "calib-ds1-UKF"


def ukf_coverage(r: Results) -> dict:
    """The UKF's 90 % coverage on clean Dataset #1 and where it comes from.

    With :data:`UKF_CALIB_STEP`: the coverage of its std rescaled on the validation
    units (the raw one beside it); without (or without validation units): the raw
    std's (``eval-ds1-UKF-clean``).

    Returns:
        ``{"value", "source", "raw", "calibrated"}`` plus the fitted ``scale`` when
        recalibrated.
    """
    raw = r.coverage("ds1", "UKF")
    calib = r.steps.get(UKF_CALIB_STEP)
    if calib is None or calib.get("coverage90") is None:  # no step, or no val units
        return {"value": raw, "source": "eval-ds1-UKF-clean (raw std)", "raw": raw,
                "calibrated": None}  # fmt: skip
    return {
        "value": calib.get("coverage90"),
        "source": f"{UKF_CALIB_STEP} (std x scale fitted on validation units "
        f"{calib.get('val_units')})",
        "raw": calib.get("coverage90_raw", raw),
        "calibrated": calib.get("coverage90"),
        "one_scale": calib.get("coverage90_one_scale"),
        "scale": calib.get("scale"),
    }


def issue_summary(r: Results) -> dict:
    """The six headline numbers of the issue (keys of :data:`GOALS`, None when
    their inputs are missing)."""
    policy = best_policy(r)
    summary = {
        "ds1_clac_over_ukf": ratio(r.theta("ds1", policy), r.theta("ds1", "UKF")),
        "ds1_bias_clac_over_ukf": ratio(
            r.theta("ds1", policy, "bias"), r.theta("ds1", "UKF", "bias")
        ),
        "ds1_policy_coverage90": r.coverage("ds1", policy),
        "ds1_ukf_coverage90": ukf_coverage(r)["value"],
        "train_to_target_s": time_to_target(
            r.train("ds1", TRAINED_AS.get(policy, policy))
        ),
        "ds1_policy_deploy_speedup_vs_ukf": ratio(
            _latency(r, "UKF"), _latency(r, policy)
        ),
    }
    return {key: _number(value) for key, value in summary.items()}


def summary_goals(summary: dict) -> dict:
    """Each goal of :data:`GOALS` and whether ``summary`` meets it.

    Returns:
        key -> ``{"min", "max", "met"}``; ``met`` is None when the number is missing.
    """
    goals = {}
    for key, (low, high) in GOALS.items():
        value = summary.get(key)
        met = None
        if value is not None:
            met = (low is None or value >= low) and (high is None or value <= high)
        goals[key] = {"min": low, "max": high, "met": met}
    return goals


def training_details(r: Results) -> dict:
    """Whose training ``train_to_target_s`` is, and what else the policy needs: the
    gate's anchor (the paper's CLAC) is trained beside its feedback, so its compute
    seconds (D fit + policy updates, all sessions) are reported with it."""
    policy = best_policy(r)
    trained = TRAINED_AS.get(policy, policy)
    details = {"policy": policy, "trained_as": trained, "anchor_train_s": None}
    if policy == "CLAC-gate" and (anchor := r.train("ds1", "CLAC")) is not None:
        fit_d = (anchor.get("surrogate") or {}).get("fit_seconds") or 0.0
        details["anchor_train_s"] = _number(fit_d + anchor.get("train_seconds", 0.0))
    return details


def summary_json(r: Results) -> dict:
    """The top-level keys ``results.json`` gains next to the steps."""
    summary = issue_summary(r)
    return {
        "summary": summary,
        "summary_goals": summary_goals(summary),
        "summary_policy": best_policy(r),
        "summary_details": {
            "ds1_ukf_coverage90": ukf_coverage(r),
            "train_to_target_s": training_details(r),
        },
    }


def _goal(low, high) -> str:
    if low is not None and high is not None:
        return f"in [{low:g}, {high:g}]"
    return f"<= {high:g}" if low is None else f">= {low:g}"


def _value(key: str, value) -> str:
    if value is None:
        return "–"
    if "coverage" in key:
        return f"{100 * value:.1f} %"
    return f"{value:.0f}" if value >= 100 else f"{value:.3g}"


def summary_section(r: Results) -> list[str]:
    """Section "The RL calibrator (issue 15)": the summary beside goals and paper."""
    summary = issue_summary(r)
    goals = summary_goals(summary)
    policy = best_policy(r)
    marks = {True: "yes", False: "**no**", None: "–"}
    rows = [
        [LABELS[key], f"`{key}`", _value(key, summary[key]), _goal(*GOALS[key]),
         marks[goals[key]["met"]], _value(key, PAPER_SUMMARY[key])]
        for key in GOALS
    ]  # fmt: skip
    met = sum(g["met"] is True for g in goals.values())
    known = sum(g["met"] is not None for g in goals.values())
    return [
        f"The policy is **{NAMES.get(policy, policy)}**"
        + ("" if policy == BEST_POLICIES[0] else f" ({BEST_POLICIES[0]} not run)")
        + f"; goals met: {met} of {known} measured ({len(GOALS)} in all). "
        "`results.json` holds these numbers under `summary` and `summary_goals`.",
        "",
        *table(["quantity", "key", "ours", "goal", "met", "paper"], rows),
        "",
        _ukf_coverage_note(r),
        "",
        "Paper: CLAC / UKF theta RMSE on its Dataset #1 and under its model bias, its "
        "total CLAC training time and its UKF / CLAC seconds per sample; it reports "
        "no intervals. CLAC-gate is CLAC-inc (incremental actions through F) while F "
        "fits the data and the paper's CLAC where it does not: the gate opens when, "
        "within the last 2 samples, the prediction error was below what the anchor's "
        "90 % interval could explain (its half-width times the feedback's "
        "sensitivity; fitted on the validation units, `fit-ds1-CLAC-gate`); it "
        "trains nothing of its own, so its time to target is CLAC-inc's (the default "
        "`make train`)" + _anchor_note(r) + ". Training time to target: the job's "
        "`time_to_target_s` (`final.json`). What each lever of the formulation gave, "
        "and why the goals not met are not: "
        "[results/train/feedback.md](../train/feedback.md).",
    ]


def _anchor_note(r: Results) -> str:
    seconds = training_details(r)["anchor_train_s"]
    if seconds is None:
        return ""
    return (
        f"; its anchor, the paper's CLAC, is a training of its own ({seconds:,.0f} s "
        "of D fit and policy updates here, 150 chunks; `summary_details`)"
    )


def _ukf_coverage_note(r: Results) -> str:
    """Which UKF coverage the summary shows, with the other one beside it."""
    cov = ukf_coverage(r)
    raw = "–" if cov["raw"] is None else f"{100 * cov['raw']:.2f} %"  # 99.99 %
    if cov["calibrated"] is None:
        return (f"UKF coverage: its raw std (q = r = 0.01), {raw}; no "
                f"`{UKF_CALIB_STEP}` step recalibrated it.")  # fmt: skip
    return (
        f"UKF coverage: its std times a scale fitted by split conformal on the "
        f"validation units (`{UKF_CALIB_STEP}`, `summary_details`), "
        f"{_value('coverage', cov['calibrated'])}; the paper's raw std "
        f"(q = r = 0.01) covers {raw}. The UKF's estimate is unchanged."
    )
