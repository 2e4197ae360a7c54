"""Early stopping of a training session (``budget.patience``) and the report of what
training added to its untrained start (issue 41)."""

import pytest

from jaxcal.cli.train import format_final
from jaxcal.training.config import resolve_config
from jaxcal.training.scoring.final_report import training_gain
from jaxcal.training.stages.policy import ChunkScoring, _out_of_patience

KEY = "val_sim_theta_rmse"


def _records(*scores):
    """Records of chunks 0.. with the given selection scores (None: not scored)."""
    return [
        {"step": i} if v is None else {"step": i, KEY: v} for i, v in enumerate(scores)
    ]


@pytest.mark.parametrize(
    "scores, patience, out",
    [
        ((1.0, 2.0), 2, False),  # one scoring after the start: not yet
        ((1.0, 2.0, 1.5), 2, True),  # two in a row not below the start's 1.0
        ((1.0, 2.0, 0.9), 2, False),  # the second one improves
        ((1.0, 0.5, 0.7, 0.6), 2, True),  # two in a row not below the best 0.5
        ((1.0, 0.5, 0.7, 0.4), 2, False),
        ((1.0, None, 2.0, None, 3.0), 2, True),  # unscored chunks do not count
        ((1.0, 2.0, 3.0), None, False),  # off
        ((1.0, 1.0), 1, True),  # equal is no improvement
    ],
)
def test_patience_counts_scorings_without_a_better_policy(scores, patience, out):
    scoring = ChunkScoring(best_key=KEY, patience=patience)
    assert _out_of_patience(_records(*scores), scoring) is out


def test_patience_is_validated():
    with pytest.raises(ValueError, match="budget.patience"):
        resolve_config(["dataset=tiny", "budget.patience=0"])
    assert resolve_config(["dataset=tiny", "budget.patience=3"]).budget.patience == 3


def test_training_gain_says_whether_training_beat_its_start():
    cfg = resolve_config(["dataset=tiny", "budget.select=sim_theta"])
    records = _records(1.0, 2.0, 0.8, 0.9)
    gain = training_gain(records, 2, cfg)
    assert gain["ratio"] == pytest.approx(0.8) and not gain["kept_start"]
    assert gain["best_trained_chunk"] == 2
    kept_start = training_gain(_records(1.0, 2.0, 1.5), 0, cfg)
    assert kept_start["kept_start"] and kept_start["best_trained"] == 1.5
    unscored = training_gain(_records(None, 2.0), 1, cfg)  # the start not scored
    assert unscored == {"start_is": unscored["start_is"], "scored": False}
    line = format_final(_final(unscored)).splitlines()
    assert sum("was not scored" in ln for ln in line) == 1
    random = {"start_is": "a randomly initialised actor", "scored": False}
    line = format_final(_final(random)).splitlines()
    assert sum("budget.score_random_start=true" in ln for ln in line) == 1
    line = format_final(_final(kept_start)).splitlines()
    assert sum("did not improve on its untrained start" in ln for ln in line) == 1
    line = format_final(_final(gain)).splitlines()
    assert sum("improved on its untrained start" in ln for ln in line) == 1
    assert any("1.000e+00 -> 8.000e-01 (0.80x)" in ln for ln in line)


def _final(gain: dict) -> dict:
    """The fields format_final reads, with ``training_gain``."""
    return {
        "run": "r", "agent": "clac", "dynamics": "physics", "chunks": 3,
        "num_updates": 1, "env_steps": 1, "test_units": [7],
        "test": {"theta_rmse": None, "tracking_rmse_norm": 0.1,
                 "tracking_rmse_units": {"y": 0.1}},
        "val_last": {}, "policy": "target", "selected_chunk": 0,
        "select": "sim_theta", "training_gain": gain,
    }  # fmt: skip


def test_training_windows_fit_the_longest_unit():
    """A unit of 200 rows holds no window of the default 200 steps (202 rows): the
    episodes were all drawn on the first unit and ran past its end. The windows are
    shortened instead, and the log says so."""
    from jaxcal.training.pipeline import fit_episode

    cfg = resolve_config(["dataset=tiny", "env.episode_length=200"])
    said = []
    fitted = fit_episode(cfg, 200, said.append)
    assert fitted.env.episode_length == 198 and "198 steps" in said[0]
    assert fit_episode(cfg, 202, said.append) is cfg and len(said) == 1
    with pytest.raises(ValueError, match="needs at least 3"):
        fit_episode(cfg, 2, said.append)


def test_the_last_scored_chunk_is_reported_from_its_validation_scores():
    """final.json's ``val_last``: the last scored chunk's validation scores (no test
    pass of its own), and the console line names them."""
    from jaxcal.training.scoring.final_report import _last_val

    records = [
        {"step": 5, "val_theta_rmse": 2.0, "val_tracking_rmse_norm": 0.2},
        {"step": 6, "cost": 1.0},
        {"step": 10, "val_theta_rmse": 1.0, "val_tracking_rmse_norm": 0.1},
        {"step": 11, "cost": 0.5},
    ]
    last = _last_val(records)
    assert last == {"chunk": 10, "theta_rmse": 1.0, "tracking_rmse_norm": 0.1}
    assert _last_val([{"step": 1, "cost": 1.0}]) == {}
    text = format_final({**_final({}), "val_last": last})
    assert "last scored chunk (10)'s validation theta RMSE 1.000e+00" in text
