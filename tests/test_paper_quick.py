"""``experiments/paper.py preset=quick``: the whole reproduction pipeline, small.

Data generation, smoke trainings through the training CLI, the E2E fits, every
evaluation, the figures and the report run once into ``tmp_path`` (about 1.5 minutes
with a warm compilation cache); a second run must skip every step.
"""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEADINGS = (
    "## 1. Inference accuracy",
    "## 2. Deployment and training time",
    "## 3. Robustness to model inadequacy",
    "## 4. Robustness to sensor noise",
    "## 5. Tracking accuracy",
    "## 6. Ablation: LAC vs CLAC",
    "## 7. Scalability",
    "## Figures",
    "## Where our CLAC loses to a baseline",
    "## Set-up",
    "## Step timings",
)
FIGURES = (
    "theta_ds1_UKF.png",
    "theta_ds1_E2E.png",
    "theta_ds1_CLAC.png",
    "theta_ds1_LAC.png",
    "tracking_ds1.png",
    "theta_ds1_bias.png",
    "theta_ds2.png",
)


def _load_paper():
    spec = importlib.util.spec_from_file_location(
        "paper_script", ROOT / "experiments" / "paper.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve annotations through it
    spec.loader.exec_module(module)
    return module


def _args(out) -> list[str]:
    """The quick run's arguments."""
    return ["preset=quick", f"out={out}"]


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    paper = _load_paper()
    out = tmp_path_factory.mktemp("paper") / "quick"
    assert paper.main(_args(out)) == 0
    return paper, out


def test_quick_preset_writes_every_table_and_figure(quick):
    _, out = quick
    report = (out / "REPORT.md").read_text()
    for heading in HEADINGS:
        assert heading in report, heading
    for name in FIGURES:
        data = (out / "figures" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name
        assert f"(figures/{name})" in report
    assert "| UKF on F |" in report and "| E2E-sim (simulated labels) |" in report
    assert "Smoke run, not results" in report
    assert "## The RL calibrator (issue 15)" in report
    assert "| CLAC-inc (increments through F) |" in report
    assert "| CLAC-gate (CLAC-inc, CLAC where F misfits) |" in report


def test_quick_steps_hold_scores_and_the_perturbations_act(quick):
    _, out = quick
    steps = {p.stem: json.loads(p.read_text()) for p in (out / "steps").glob("*.json")}
    clean = steps["eval-ds1-UKF-clean"]
    assert clean["theta_finite"] and clean["tracking_rmse_norm"] < 0.05
    # the model perturbations reach the UKF's model, the sensor noise its data
    for variant in ("bias", "noise", "snr70"):
        assert steps[f"eval-ds1-UKF-{variant}"]["theta_rmse"] != clean["theta_rmse"]
    assert steps["eval-ds1-UKF-bias"]["theta_rmse"] > 5 * clean["theta_rmse"]
    # the E2E network has no model: the model perturbations are not run for it
    assert "eval-ds1-E2E-bias" not in steps
    for agent in ("CLAC", "LAC", "SAC"):
        ev = steps[f"eval-ds1-{agent}-clean"]
        assert Path(ev["info"]["run"]).is_dir() and ev["num_samples"] == 40
    assert steps["train-ds1-clac"]["argv"][:2] == ["dataset=tiny", "agent=clac"]
    assert steps["latency-ds1-UKF"]["median_s"] > 0
    assert set(steps["figures"]["figures"]) >= set(FIGURES)
    # the UKF's std reaches its scores; the summary sits beside the steps
    assert 0.0 <= clean["coverage90"] <= 1.0
    results = json.loads((out / "results.json").read_text())
    summary = results["summary"]
    # ... rescaled on the validation units (calib-ds1-UKF), the raw one kept beside
    calib = steps["calib-ds1-UKF"]
    assert calib["theta_rmse"] == pytest.approx(clean["theta_rmse"], rel=1e-9)
    assert calib["coverage90_raw"] == pytest.approx(clean["coverage90"])
    assert summary["ds1_ukf_coverage90"] == calib["coverage90"] is not None
    details = results["summary_details"]["ds1_ukf_coverage90"]
    assert details["raw"] == calib["coverage90_raw"]
    assert summary["ds1_clac_over_ukf"] > 0 and len(summary) == 6
    assert set(results["summary_goals"]) == set(summary)
    assert results["summary_policy"] == "CLAC-gate"
    for variant in ("bias", "noise", "snr70"):
        assert f"eval-ds1-CLAC-inc-{variant}" in steps
        assert f"eval-ds1-CLAC-gate-{variant}" in steps
    assert "latency-ds1-CLAC-inc" in steps and "latency-ds1-CLAC-gate" in steps
    gate = steps["fit-ds1-CLAC-gate"]
    assert gate["val_units"] and gate["sensitivity"][0] > 0
    assert "time_to_target_s" in steps["train-ds1-clac-inc"]
    # the run's calibrated band reaches the deployed policy's scores
    inc = steps["eval-ds1-CLAC-inc-clean"]
    assert 0.0 <= inc["coverage90"] <= 1.0 and inc["theta_std_median"] > 0
    gated = steps["eval-ds1-CLAC-gate-clean"]
    assert 0.0 <= gated["coverage90"] <= 1.0 and gated["theta_finite"]
    assert summary["ds1_policy_coverage90"] == gated["coverage90"]
    train = steps["train-ds1-clac-inc"]
    assert (
        "dynamics=physics" in train["argv"] and "env.action=increment" in train["argv"]
    )
    # the NPE peer runs when its optional extra (sbi) is installed, else is absent
    report = (out / "REPORT.md").read_text()
    assert "## Amortised inference peer (NPE, sbi" in report
    if importlib.util.find_spec("sbi") is None:
        assert "eval-ds1-NPE-clean" not in steps and "pip install" in report
    else:
        npe = steps["eval-ds1-NPE-clean"]
        assert npe["num_samples"] == 40 and 0.0 <= npe["coverage90"] <= 1.0
        assert npe["theta_finite"] and steps["latency-ds1-NPE"]["median_s"] > 0
        assert "| NPE (maf, sbi) |" in report


def test_rerun_skips_every_step_and_bad_arguments_fail(quick, capsys):
    paper, out = quick
    capsys.readouterr()
    assert paper.main(_args(out)) == 0
    printed = capsys.readouterr().out
    num_steps = len(list((out / "steps").glob("*.json")))
    assert "[step]" not in printed and printed.count("[skip]") == num_steps
    assert paper.main(["preset=nope"]) == 2
    assert paper.main(["bogus=1"]) == 2
