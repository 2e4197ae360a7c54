"""The CPU benchmark (experiments/bench_cpu.py) at tiny sizes: every section runs and
the JSON document is well formed. No wall-clock assertion (the machine is shared), and
no optional peer is needed: ``--no-optional-peers`` gives what CI (``.[dev]`` only)
sees, figures whose peer has no number stating why."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "experiments" / "bench_cpu.py"
SECTIONS = {"policy", "training", "engine", "ukf", "end_to_end"}

sys.path.insert(0, str(ROOT / "experiments"))
from cpubench.measure import figure, missing_peer, peer  # noqa: E402


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """``(stdout document, written document)`` of one ``--quick`` run."""
    tmp = tmp_path_factory.mktemp("bench_cpu")
    out = tmp / "bench_cpu.json"
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        # A private compilation cache, and unoptimised XLA code: compiling is most of
        # a quick run and the speed of the result is irrelevant here.
        "JAXCAL_CACHE_DIR": str(tmp / "xla"),
        "XLA_FLAGS": (
            os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
        ).strip(),
    }
    command = [sys.executable, str(SCRIPT), "--quick", "--no-optional-peers"]
    proc = subprocess.run(
        command + ["--out", str(out)],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout), json.loads(out.read_text())


def _figures(doc):
    for name, section in doc["sections"].items():
        for key, fig in section["figures"].items():
            yield f"{name}.{key}", fig


def test_quick_run_prints_the_document_it_writes(quick_run):
    printed, written = quick_run
    assert printed == written
    assert printed["quick"] is True and printed["optional_peers"] is False
    assert set(printed["sections"]) == SECTIONS
    assert printed["summary_ratios"] == {
        name: fig["ratio"] for name, fig in _figures(printed)
    }


def test_every_section_reports_machine_state_and_figures(quick_run):
    doc, _ = quick_run
    for name, section in doc["sections"].items():
        assert section["figures"], name
        machine = section["machine"]
        assert {"steal_fraction", "busy_fraction", "loadavg_1min", "seconds"} <= set(
            machine
        )
    assert doc["machine"]["OPENBLAS_NUM_THREADS"] == "1"


def test_every_figure_has_value_peer_and_ratio_or_reason(quick_run):
    doc, _ = quick_run
    for name, fig in _figures(doc):
        assert {"value", "unit", "better", "peer", "ratio"} <= set(fig), name
        assert fig["better"] in ("higher", "lower"), name
        assert "name" in fig["peer"] and "value" in fig["peer"], name
        if fig["ratio"] is None:
            assert isinstance(fig.get("reason"), str) and fig["reason"], name
            continue
        ours, theirs = fig["value"], fig["peer"]["value"]
        assert ours > 0 and theirs > 0, name
        expected = ours / theirs if fig["better"] == "higher" else theirs / ours
        assert math.isclose(fig["ratio"], expected, rel_tol=1e-9), name


def test_quick_run_measures_ours_and_names_missing_peers(quick_run):
    doc, _ = quick_run
    figs = dict(_figures(doc))
    # numpy is always there: the policy figures carry real ratios
    for key in ("single_sample_latency", "batched_throughput", "batched_gflops"):
        assert figs[f"policy.{key}"]["ratio"] > 0
    # ours is measured even when the optional peer is disabled, which is said
    clac = figs["training.clac_updates_per_s"]
    assert clac["value"] > 0 and "disabled" in clac["reason"]
    assert figs["ukf.toy_single_vs_dynamax"]["value"] > 0
    assert "--quick" in figs["engine.batched"]["reason"]
    assert "--quick" in figs["ukf.engine_single_vs_filterpy"]["reason"]
    # published reference numbers are labelled as such
    deploy = figs["end_to_end.deployment_single_stream"]
    assert deploy["peer"]["published"] is True and deploy["ratio"] > 0


def test_figure_ratio_means_jaxcal_is_better_above_one():
    fast = figure(2.0, "us", "lower", peer("p", 8.0, "us", 6.0), best=1.0)
    assert fast["ratio"] == 4.0 and fast["ratio_best"] == 6.0
    rate = figure(300.0, "1/s", "higher", peer("p", 100.0, "1/s"))
    assert rate["ratio"] == 3.0 and rate["ratio_best"] is None
    absent = figure(5.0, "us", "lower", missing_peer("p", "not installed"))
    assert absent["ratio"] is None and absent["reason"] == "not installed"
    with pytest.raises(ValueError, match="better"):
        figure(1.0, "s", "faster", peer("p", 1.0, "s"))


def test_training_figures_report_time_to_target_beside_the_paper():
    from cpubench.end_to_end import training_figures

    final = {"wall_seconds": 500.0, "target_theta_rmse": 2.5e-4,
             "time_to_target_s": 310.0, "time_to_target_chunk": 60,
             "target_scorings": 30, "test": {"theta_rmse": 2e-4}}  # fmt: skip
    figs = training_figures(final, "runs/x/final.json")
    to_target = figs["train_to_target_s"]
    assert to_target["value"] == 310.0 and to_target["peer"]["value"] == 6200.0
    assert to_target["ratio"] == pytest.approx(6200.0 / 310.0)
    assert to_target["chunk"] == 60 and "reason" not in to_target
    missed = training_figures({**final, "time_to_target_s": None}, "f.json")
    assert missed["train_to_target_s"]["ratio"] is None
    assert "never reached" in missed["train_to_target_s"]["reason"]
    old = {k: v for k, v in final.items() if k != "time_to_target_s"}
    assert "predates" in training_figures(old, "f.json")["train_to_target_s"]["reason"]
    absent = training_figures(None, "no final.json")
    assert all(fig["reason"] == "no final.json" for fig in absent.values())
