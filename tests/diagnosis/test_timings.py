"""Progress and timings of the diagnosis (issue 43 item 5): a progress line per stage
and per batch of rows on stderr, each stage's wall seconds in report.json."""

import io
import json

import test_diagnose_any_model as any_model
from test_diagnose_any_model import _write_csv

from jaxcal.cli.diagnose import main
from jaxcal.diagnosis.pipeline import STAGES
from jaxcal.diagnosis.timing import StageClock, batch_progress


def test_report_json_holds_the_seconds_of_every_stage(tmp_path, capsys):
    data = _write_csv(tmp_path / "pump.csv", t_out_bias=0.5)
    out = tmp_path / "out"
    argv = [f"model={any_model.__file__}:PUMP", f"data={data}", "calibrate=wear",
            f"out={out}"]  # fmt: skip
    assert main(argv) == 0
    timings = json.loads((out / "report.json").read_text())["timings"]
    assert list(timings) == [*STAGES, "total"]
    assert all(v >= 0.0 for v in timings.values())
    assert sum(timings[s] for s in STAGES) <= timings["total"] + 0.01
    assert timings["calibrate"] > 0.0  # the declared-only fit evaluates the model
    err = capsys.readouterr().err
    for stage in STAGES:  # one line as each stage starts (stderr is not a terminal)
        assert f"diagnosis: {stage}" in err, err
    assert "rows 200/200" in err  # the batches of the fleet's rows evaluated


def test_a_stage_entered_twice_adds_up_and_lines_need_a_clock():
    stream = io.StringIO()
    batch_progress(1, 2)  # no diagnosis running: nothing happens
    clock = StageClock(progress=True, file=stream)
    with clock.stage("fit"):
        batch_progress(128, 256, "rows")
    with clock.stage("fit"):
        pass
    with clock.stage("screen"):
        pass
    clock.close()
    batch_progress(1, 2)  # closed: no line, no error
    timings = clock.timings()
    assert list(timings) == ["fit", "screen", "total"]
    assert timings["fit"] <= timings["total"]
    lines = stream.getvalue().splitlines()
    assert any(line.startswith("diagnosis: fit") for line in lines), lines
    assert any(line.startswith("diagnosis: screen") for line in lines), lines
    assert all("\r" not in line for line in lines)
    quiet = StageClock(progress=False)
    with quiet.stage("fit"):
        batch_progress(1, 1)
    quiet.close()
    assert list(quiet.timings()) == ["fit", "total"]
