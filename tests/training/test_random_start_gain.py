"""A run whose actor has no prior (the turbofan's: a randomly initialised network)
reports what training gained over its untrained start with
``budget.score_random_start=true`` (one more validation pass; by default it says the
start was not scored), and ``budget.num_chunks=0`` gives it a deployable untrained
policy."""

import json

import pytest
from support.synthetic_file import write_synthetic_ncmapss

from jaxcal.cli.train import main
from jaxcal.runs.metrics_log import read_metrics

START_IS = "a randomly initialised actor"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("start_gain")
    path = write_synthetic_ncmapss(root / "synthetic.h5")
    argv = [
        "dataset=ncmapss", "preset=smoke", f"path={path}", "dataset.stride=1",
        f"output.runs_dir={root / 'runs'}", "output.progress=false",
    ]  # fmt: skip
    return argv, root / "runs"


def _final(runs_dir, name) -> dict:
    return json.loads((runs_dir / name / "final.json").read_text())


def test_the_gain_over_a_random_start_is_reported_and_matches_the_start_run(
    runs, capsys
):
    argv, runs_dir = runs
    assert main([*argv, "name=trained", "budget.score_random_start=true"]) == 0
    out = capsys.readouterr().out
    gain = _final(runs_dir, "trained")["training_gain"]
    assert gain["scored"]
    assert gain["start_is"] == START_IS and gain["key"] == "val_tracking_rmse_norm"
    assert not gain["kept_start"] and gain["ratio"] == pytest.approx(
        gain["kept"] / gain["start"]
    )
    # scored after the training: the metrics keep their trained chunks only
    steps = [r["step"] for r in read_metrics(runs_dir / "trained" / "metrics.jsonl")]
    assert steps == [1, 2]
    said = [ln for ln in out.splitlines() if f"untrained start ({START_IS}):" in ln]
    assert len(said) == 1 and said[0].startswith("training ")

    # the same seed untrained: its chunk 0 is the start the trained run scored
    assert main([*argv, "name=start", "budget.num_chunks=0"]) == 0
    out = capsys.readouterr().out
    start = _final(runs_dir, "start")
    assert start["selected_chunk"] == 0 and start["training_gain"]["kept_start"]
    assert start["training_gain"]["start"] == pytest.approx(gain["start"], rel=1e-5)
    assert "did not improve on its untrained start" in out
    # deployable: the untrained policy was kept as chunk 0
    from jaxcal.calibrators.methods.policy.loading import load_run

    assert load_run(runs_dir / "start").step == 0
