"""The robust identification study's machinery at a tiny size
(experiments/loop_robust.py): randomised records, detectability sizes, the resumable
record file and the summary."""

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "experiments"))

import loop_robust  # noqa: E402
import robust_scenario as rs  # noqa: E402

SENSORS = ("T24", "T30", "T50", "P30")


def test_scenario_draws_what_the_diagnosis_does_not_assume():
    draws = [rs.draw_setting(np.random.default_rng(s), 4) for s in range(40)]
    assert {d.profile for d in draws} == set(rs.PROFILES)
    assert {w[0] for d in draws for w in d.wear} == set(rs.SHAPES)
    assert any(d.phi == 0.0 for d in draws) and any(d.phi > 0.3 for d in draws)
    assert any(len(d.carriers) < d.units for d in draws)
    assert all(0.5 <= d.noise_factor <= 2.0 for d in draws)
    t = np.linspace(0.0, 1.0, 11)
    for shape, p in (("linear", 0.0), ("exponential", 3.0), ("piecewise", 0.4)):
        g = rs.wear_shape(shape, p, t)
        assert (
            abs(g[0]) < 1e-12 and abs(g[-1] - 1.0) < 1e-12 and np.all(np.diff(g) >= 0)
        )


def test_tiny_study_resumes_and_summarises(tmp_path, engine):
    argv = [f"out={tmp_path}", "seeds=1", "clean=1", "multiples=1,10",
            "kinds=sensor_bias", f"sensors={','.join(SENSORS)}", "max_units=2",
            "max_life=30"]  # fmt: skip
    assert loop_robust.main(argv) == 0
    rows = [
        json.loads(x) for x in (tmp_path / "records.jsonl").read_text().splitlines()
    ]
    assert [(r["kind"], r["multiple"]) for r in rows] == [
        ("none", 0.0),
        ("sensor_bias", 1.0),
        ("sensor_bias", 10.0),
    ]
    s1 = json.loads((tmp_path / "detectability.json").read_text())["sensor_bias"]
    assert set(s1) == set(SENSORS) and all(v > 0 for v in s1.values())
    big = rows[2]
    assert abs(abs(big["size"]) - 10 * s1[big["target"]]) < 1e-9 * s1[big["target"]]
    assert big["first"], big  # at 10x the detectability size the bias is found
    assert set(big["flagged"]) <= set(big["units"])
    summary = json.loads((tmp_path / "study.json").read_text())["summary"]
    assert summary["kinds"]["sensor_bias"]["10.0"]["identified"] == 1.0
    assert summary["false_alarm_n"] == 1
    assert (tmp_path / "detection.png").stat().st_size > 1000
    assert loop_robust.main(argv) == 0  # resumed: nothing is rerun
    assert len((tmp_path / "records.jsonl").read_text().splitlines()) == 3
