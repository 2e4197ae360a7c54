"""Interval coverage in the evaluation, and the issue's summary in the report.

A toy calibrator whose error is Gaussian with a known std shows that ``coverage90``
lands near its nominal 90 % (and well below it when the reported std is too small);
the summary is checked on hand-built step dicts: its exact keys, its numbers, null
where inputs are missing, and its section in ``REPORT.md``.
"""

import json

import jax.numpy as jnp
import numpy as np
import pytest
from support.paper_problem import paper_problem

from jaxcal.calibrators.interface import Calibrator, CalStepOutput
from jaxcal.data.padded import Padded
from jaxcal.paper.compare import evaluate_method, interval_coverage
from jaxcal.paper.methods import make_method
from jaxcal.paper.report import write_report
from jaxcal.paper.summary import (
    GOALS,
    best_policy,
    issue_summary,
    summary_goals,
    summary_json,
)
from jaxcal.paper.tables import Results

THETA = ("HPT_eff_mod", "HPT_flow_mod")
SENSORS = ("T24", "T30")
SIGMA = np.array([2e-3, 5e-4])  # the toy's error std per parameter
KEYS = {
    "ds1_clac_over_ukf",
    "ds1_bias_clac_over_ukf",
    "ds1_policy_coverage90",
    "ds1_ukf_coverage90",
    "train_to_target_s",
    "ds1_policy_deploy_speedup_vs_ukf",
}


def test_interval_coverage_counts_only_scored_samples():
    theta = np.array([[[0.0], [1.0], [5.0], [0.5]]])  # [U=1, T=4, P=1]
    truth = np.zeros_like(theta)
    std = np.ones_like(theta)
    mask = np.array([[True, True, True, False]])  # the last one is not scored
    out = interval_coverage(theta, std, truth, mask, ["a"])
    assert out["coverage90"] == pytest.approx(2 / 3)  # 0 and 1 <= 1.6449, 5 is not
    assert out["coverage90_per_param"] == {"a": pytest.approx(2 / 3)}
    assert out["theta_std_median"] == 1.0
    with pytest.raises(ValueError, match="theta_std"):
        interval_coverage(theta, std[..., :0], truth, mask, ["a"])
    empty = interval_coverage(theta, std, truth, np.zeros_like(mask), ["a"])
    assert empty["coverage90"] is None


def _toy_units(num_units=3, num_steps=1500, seed=0) -> Padded:
    """x = theta + SIGMA * eps: a calibrator reading theta off x errs by SIGMA."""
    rng = np.random.default_rng(seed)
    theta = -np.cumsum(rng.uniform(0, 1e-5, (num_units, num_steps, 2)), axis=1)
    x = theta + SIGMA * rng.standard_normal(theta.shape)
    x[0, 5] = np.nan  # a flagged sample: not scored, not counted as covered
    lengths = np.array([num_steps, num_steps - 100, num_steps - 300], np.int32)
    w = np.tile(np.array([20_000.0, 0.5, 60.0, 500.0]), (num_units, num_steps, 1))
    return Padded(
        w=w, x=x, theta=theta, lengths=lengths, unit_ids=np.arange(1, num_units + 1)
    )


def _toy_method(std_factor: float | None):
    """Reads theta off x; reports ``std_factor * SIGMA`` (None: no std)."""

    def build(bias, noise_sigma):
        del bias, noise_sigma

        def init(key, w0, x0):
            return jnp.zeros(())

        def step(state, w_t, x_t):
            aux = None
            if std_factor is not None:
                aux = {"theta_std": jnp.asarray(std_factor * SIGMA, x_t.dtype)}
            return state, CalStepOutput(theta=x_t, xhat=x_t, aux=aux)

        return Calibrator(init, step)

    return make_method("toy", build, jnp.float32, {})


def test_evaluation_reports_coverage_near_nominal_for_a_known_std():
    units = _toy_units()
    x_valid = np.nan_to_num(units.x[units.mask])
    problem = paper_problem(
        "toy", SENSORS, THETA, [-0.02, -0.02], [0.0, 0.0], x_valid.mean(0),
        x_valid.std(0) + 1e-6,
    )  # fmt: skip
    honest = evaluate_method(_toy_method(1.0), units, problem).scores
    scored = honest["num_scored"]
    assert scored == units.mask.sum() - 1  # the NaN sample is flagged, not scored
    # binomial std of a share over ~3,600 samples is 0.005: 0.9 +- 0.02 is 4 stds
    assert honest["coverage90"] == pytest.approx(0.9, abs=0.02)
    for name in THETA:
        assert honest["coverage90_per_param"][name] == pytest.approx(0.9, abs=0.025)
    assert honest["theta_std_median"] == pytest.approx(np.median(SIGMA), rel=1e-6)
    # a band half as wide covers P(|eps| <= 0.822) = 0.589
    narrow = evaluate_method(_toy_method(0.5), units, problem).scores
    assert narrow["coverage90"] == pytest.approx(0.589, abs=0.025)
    none = evaluate_method(_toy_method(None), units, problem).scores
    assert "coverage90" not in none and "theta_std_median" not in none
    assert none["theta_rmse"] == pytest.approx(honest["theta_rmse"])


# ------------------------------------------------------------------ summary


def _eval(method, theta, variant="clean", coverage=None):
    ev = {
        "dataset": "ds1",
        "variant": variant,
        "method": method,
        "theta_rmse": theta,
        "tracking_rmse_norm": 0.01,
        "theta_rmse_per_param": {"HPT_eff_mod": theta},
        "theta_rmse_per_unit": {"7": theta},
        "units": [7],
        "num_samples": 10,
        "batched_samples_per_s": 1000.0,
        "info": {},
        "seconds": 1.0,
        "estimate_s": 2.0,
    }
    if coverage is not None:
        ev.update(coverage90=coverage, coverage90_per_param={"HPT_eff_mod": coverage})
    return ev


def _latency(median_s):
    return {"median_s": median_s, "min_s": median_s, "repeats": 3, "seconds": 1.0,
            "estimate_s": 1.0}  # fmt: skip


def _train(agent, time_to_target_s, run_dir):
    return {
        "run_dir": str(run_dir), "argv": [f"agent={agent}"], "seed": 0, "chunks": 3,
        "stopped_early": False, "selected_chunk": 3, "reused": False,
        "train_seconds": 100.0, "wall_seconds": 120.0, "seconds": 120.0,
        "estimate_s": 100.0, "time_to_target_s": time_to_target_s,
    }  # fmt: skip


def _steps(tmp_path, with_inc=True):
    steps = {
        "train-ds1-clac": _train("clac", None, tmp_path / "clac"),
        "eval-ds1-UKF-clean": _eval("UKF", 1e-4, coverage=0.9),
        "eval-ds1-UKF-bias": _eval("UKF", 8e-3, "bias", coverage=0.01),
        "eval-ds1-CLAC-clean": _eval("CLAC", 4e-3),
        "eval-ds1-CLAC-bias": _eval("CLAC", 8e-4, "bias"),
        "latency-ds1-UKF": _latency(1.2e-3),
        "latency-ds1-CLAC": _latency(2e-4),
    }
    if with_inc:
        steps |= {
            "train-ds1-clac-inc": _train("clac", 450.0, tmp_path / "inc"),
            "eval-ds1-CLAC-inc-clean": _eval("CLAC-inc", 2e-4, coverage=0.8),
            "eval-ds1-CLAC-inc-bias": _eval("CLAC-inc", 1e-3, "bias", coverage=0.7),
            "latency-ds1-CLAC-inc": _latency(1e-4),
        }
    return steps


def test_summary_takes_the_best_policy_and_checks_the_goals(tmp_path):
    summary = issue_summary(Results(_steps(tmp_path)))
    assert set(summary) == KEYS == set(GOALS)
    assert summary == pytest.approx(
        {
            "ds1_clac_over_ukf": 2.0,  # CLAC-inc, not CLAC (40)
            "ds1_bias_clac_over_ukf": 0.125,
            "ds1_policy_coverage90": 0.8,
            "ds1_ukf_coverage90": 0.9,
            "train_to_target_s": 450.0,
            "ds1_policy_deploy_speedup_vs_ukf": 12.0,
        }
    )
    goals = summary_goals(summary)
    assert {k: g["met"] for k, g in goals.items()} == {
        "ds1_clac_over_ukf": True,
        "ds1_bias_clac_over_ukf": True,
        "ds1_policy_coverage90": False,  # below 0.85
        "ds1_ukf_coverage90": True,
        "train_to_target_s": True,
        "ds1_policy_deploy_speedup_vs_ukf": True,
    }
    assert goals["ds1_policy_coverage90"]["min"] == 0.85


def test_the_gated_policy_is_summarised_with_its_feedbacks_training(tmp_path):
    steps = _steps(tmp_path) | {
        "eval-ds1-CLAC-gate-clean": _eval("CLAC-gate", 1e-4, coverage=0.9),
        "eval-ds1-CLAC-gate-bias": _eval("CLAC-gate", 8e-4, "bias", coverage=0.9),
        "latency-ds1-CLAC-gate": _latency(2e-4),
    }
    r = Results(steps)
    assert best_policy(r) == "CLAC-gate"
    summary = issue_summary(r)
    assert summary["ds1_clac_over_ukf"] == pytest.approx(1.0)
    assert summary["ds1_bias_clac_over_ukf"] == pytest.approx(0.1)
    assert summary["train_to_target_s"] == 450.0  # CLAC-inc's training
    assert summary["ds1_policy_deploy_speedup_vs_ukf"] == pytest.approx(6.0)
    # the anchor's own training is reported beside the feedback's time to target
    steps["train-ds1-clac"]["surrogate"] = {"fit_seconds": 20.0}
    details = summary_json(Results(steps))["summary_details"]["train_to_target_s"]
    assert details == {
        "policy": "CLAC-gate",
        "trained_as": "CLAC-inc",
        "anchor_train_s": 120.0,
    }


def test_summary_falls_back_to_clac_and_is_null_where_inputs_are_missing(tmp_path):
    steps = _steps(tmp_path, with_inc=False)
    del steps["latency-ds1-UKF"], steps["eval-ds1-UKF-bias"]
    summary = issue_summary(Results(steps))
    assert set(summary) == KEYS
    assert summary["ds1_clac_over_ukf"] == pytest.approx(40.0)
    for key in ("ds1_bias_clac_over_ukf", "ds1_policy_coverage90",
                "train_to_target_s", "ds1_policy_deploy_speedup_vs_ukf"):  # fmt: skip
        assert summary[key] is None, key
    assert summary_goals(summary)["train_to_target_s"]["met"] is None
    # a train step without the key: the run's final.json is read
    (tmp_path / "clac").mkdir()
    (tmp_path / "clac" / "final.json").write_text(json.dumps({"time_to_target_s": 75}))
    steps["train-ds1-clac"].pop("time_to_target_s")
    assert issue_summary(Results(steps))["train_to_target_s"] == 75.0
    assert issue_summary(Results({}))["ds1_clac_over_ukf"] is None


def test_report_writes_the_summary_and_the_new_columns(tmp_path):
    steps = _steps(tmp_path)
    path = write_report(
        tmp_path / "REPORT.md", steps, preset="test", description="toy", seed=0,
        command="test", wall_seconds=1.0,
    )  # fmt: skip
    text = path.read_text()
    section = text.index("## The RL calibrator (issue 15)")
    assert section < text.index("## 1. Inference accuracy")
    assert "The policy is **CLAC-inc" in text
    assert "| `ds1_clac_over_ukf` | 2 | <= 3 | yes | 0.965 |" in text
    assert "| `ds1_policy_coverage90` | 80.0 % | in [0.85, 0.95] | **no** | – |" in text
    assert "| `ds1_policy_deploy_speedup_vs_ukf` | 12 | >= 5 | yes | 15000 |" in text
    assert "| CLAC-inc (increments through F) | 2.00e-04 |" in text
    assert "| UKF on F | 1.00e-04 | 3.42e-04 | – | 3.51e-03 | 90.0 % | – |" in text
    assert "| CLAC | 4.00e-03 | 3.30e-04 | – | 2.50e-03 | – | – |" in text
    assert "bias F x 1.02: CLAC-inc / UKF: ours **0.12**" in text
    assert "UKF / CLAC-inc deployment time: ours **12.00**" in text
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["summary_policy"] == "CLAC-inc"
    assert set(saved["summary"]) == KEYS
    assert saved["summary"]["train_to_target_s"] == 450
    assert saved["summary_goals"]["ds1_policy_coverage90"]["met"] is False
    assert saved["eval-ds1-UKF-clean"] == steps["eval-ds1-UKF-clean"]  # steps kept
    # no CLAC-inc: the tables still print, with dashes in its places
    write_report(
        tmp_path / "REPORT.md", _steps(tmp_path, with_inc=False), preset="test",
        description="toy", seed=0, command="test", wall_seconds=1.0,
    )  # fmt: skip
    text = (tmp_path / "REPORT.md").read_text()
    assert "The policy is **CLAC** (CLAC-gate not run)" in text
    assert "| CLAC-inc (increments through F) | – |" in text
    assert "CLAC-inc / UKF" not in text
