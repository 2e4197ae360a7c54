"""The robust identification study's machinery at a tiny size
(experiments/loop_robust.py): randomised records on three models, each record's own
detectability size, the resumable record file and summary.json's keys."""

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "experiments"))

import loop_robust  # noqa: E402
import robust_scenario as rs  # noqa: E402


def test_settings_draw_what_the_diagnosis_does_not_assume():
    sm = rs.STUDY_MODELS["heat_exchanger"]
    draws = [rs.draw(sm, np.random.default_rng(s)) for s in range(40)]
    assert {w[0] for d in draws for w in d.wear} == set(rs.SHAPES)
    assert any(d.phi == 0.0 for d in draws) and any(d.phi > 0.3 for d in draws)
    assert any(len(d.carriers) < d.units for d in draws)
    assert all(0.5 <= d.noise_factor <= 2.0 for d in draws)
    assert all(0.3 <= o <= 0.7 for d in draws for o in d.onsets)
    t = np.linspace(0.0, 1.0, 11)
    for shape, p in (("linear", 0.0), ("exponential", 3.0), ("piecewise", 0.4)):
        g = rs.wear_shape(shape, p, t)
        assert abs(g[0]) < 1e-12 and abs(g[-1] - 1.0) < 1e-12
        assert np.all(np.diff(g) >= 0)
    for sm in rs.STUDY_MODELS.values():
        assert {"parameter_step", "sensor_step", "sensor_bias"} <= set(sm.kinds)


def test_tiny_study_resumes_and_writes_the_summary_keys(tmp_path):
    argv = [f"out={tmp_path}", "models=heat_exchanger", "seeds=1", "clean=1",
            "multiples=10", "kinds=sensor_step", "max_units=2",
            "max_life=70"]  # fmt: skip
    assert loop_robust.main(argv) == 0
    rows = [json.loads(x) for x in (tmp_path / "records.jsonl").read_text().split("\n")
            if x]  # fmt: skip
    assert [(r["kind"], r["multiple"]) for r in rows] == [
        ("none", 0.0),
        ("sensor_step", 10.0),
    ]
    step = rows[1]
    assert step["s1"] > 0 and abs(abs(step["size"]) - 10 * step["s1"]) < 1e-9
    assert step["first"], step  # at 10x its detectability size the step is named
    assert set(step["flagged"]) == set(step["carriers"])
    assert all(e < 0.1 for e in step["onset_error"])
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary) == {"false_alarm_rate", "identification", "unit_hit_rate",
                            "onset_error", "per_model"}  # fmt: skip
    assert summary["identification"]["sensor_step"]["10x"] == 1.0
    assert set(summary["per_model"]["heat_exchanger"]) == set(summary) - {"per_model"}
    assert (tmp_path / "detection.png").stat().st_size > 1000
    assert loop_robust.main(argv) == 0  # resumed: nothing is rerun
    assert len((tmp_path / "records.jsonl").read_text().split("\n")) == 3
