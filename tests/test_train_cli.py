"""``python -m jaxcal.train``: argument errors, a smoke run, resume on rerun."""

import json
import subprocess
import sys

import pytest
from support.synthetic_file import write_synthetic_ncmapss

from jaxcal.cli.train import main, parse_args
from jaxcal.runs.metrics_log import read_metrics


def test_unknown_key_is_an_error_listing_the_valid_keys(capsys):
    assert main(["dataset=cmapss", "bogus=1"]) == 2
    err = capsys.readouterr().err
    assert "unknown key 'bogus'" in err
    for key in ("agent", "budget", "dynamics", "runner", "seed", "theta", "preset"):
        assert key in err
    assert main(["agent.no_such_field=1"]) == 2
    assert "valid keys of agent" in capsys.readouterr().err
    assert main(["agent=ppo"]) == 2
    assert "choose one of: sac, lac, clac" in capsys.readouterr().err
    assert main(["dynamics=quantum"]) == 2
    assert main(["seed"]) == 2


def test_parse_args_resolves_groups_aliases_and_name():
    cfg = parse_args(
        ["agent=lac", "dynamics=physics", "seed=7", "name=mine", "runner.num_envs=32"]
    )
    assert cfg.agent_name == "lac" and cfg.dynamics == "physics" and cfg.seed == 7
    assert cfg.run_name == "mine" and cfg.runner.num_envs == 32


def test_module_entry_point_prints_usage():
    out = subprocess.run(
        [sys.executable, "-m", "jaxcal.train", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "python -m jaxcal.train dataset=" in out


@pytest.fixture(scope="module")
def smoke_argv(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    path = write_synthetic_ncmapss(root / "synthetic.h5")
    return [
        "dataset=ncmapss",
        "preset=smoke",
        f"path={path}",
        "dataset.stride=1",
        f"output.runs_dir={root / 'runs'}",
        "output.progress=false",
        "name=smoke",
    ], root / "runs" / "smoke"


def test_smoke_run_writes_the_run_folder_and_resumes(smoke_argv, capsys):
    argv, run_dir = smoke_argv
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "test units [4, 5]: theta RMSE" in out and "tracking RMSE" in out
    for name in ("config.json", "data.json", "surrogate.json", "final.json"):
        assert (run_dir / name).is_file(), name
    for name in ("checkpoints", "policy", "policy_best", "surrogate"):
        assert (run_dir / name).is_dir(), name
    assert [r["step"] for r in read_metrics(run_dir / "metrics.jsonl")] == [1, 2]
    final = json.loads((run_dir / "final.json").read_text())
    assert final["chunks"] == 2 and final["wall_seconds"] > 0
    assert set(final["test"]["tracking_rmse_units"]) == set(
        json.loads((run_dir / "data.json").read_text())["sensors"]
    )
    surrogate = json.loads((run_dir / "surrogate.json").read_text())
    assert set(surrogate["test"]["free_run_rmse_norm"]) == set(
        final["test"]["tracking_rmse_units"]
    )
    # Rerunning the same command resumes: nothing left to train, same scores.
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "resuming" in out and "surrogate D restored" in out
    again = json.loads((run_dir / "final.json").read_text())
    assert again["test"] == final["test"]
    # the wall time of a run spread over sessions adds up
    assert final["sessions"] == 1 and again["sessions"] == 2
    assert again["wall_seconds_total"] == pytest.approx(
        final["wall_seconds"] + again["wall_seconds"]
    )
    # Extending the budget continues from the last checkpoint.
    assert main(argv + ["budget.num_chunks=3"]) == 0
    assert [r["step"] for r in read_metrics(run_dir / "metrics.jsonl")] == [1, 2, 3]
    # Another agent under the same name is refused.
    assert main(argv + ["agent=sac"]) == 2
    assert "different config" in capsys.readouterr().err
