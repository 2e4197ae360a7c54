"""The diagnosis on two ``jax.distributed`` processes on localhost (issue 43 item 2):
the model's evaluations split by units (:mod:`jaxcal.diagnosis.data.sharding`), every
process reaches the report of one process, to the last bit; process 0 alone writes.

A static model through ``python -m jaxcal.diagnose --num-processes 2`` (600 rows: three
row chunks, two in process 0 and one in process 1) and a model with memory through the
library (three units: two and one, padded to two).
"""

import json
import os
import sys

import numpy as np
import pytest
import test_diagnose_any_model as any_model
from support.processes import free_port, run_processes
from test_diagnose_any_model import _write_csv

from jaxcal.cli.diagnose import main, parse_args
from jaxcal.diagnosis.data import sharding

HERE = os.path.dirname(os.path.abspath(__file__))
WORKER = os.path.join(HERE, "diagnose_worker.py")


def _comparable(rep: dict) -> dict:
    """A report without what differs from run to run: wall seconds, the folder."""
    rep = {k: v for k, v in rep.items() if k not in ("timings", "out")}
    if rep.get("config"):
        rep["config"] = {
            k: v for k, v in rep["config"].items() if k not in ("seconds", "out")
        }
    return rep


@pytest.fixture(scope="module")
def static_runs(tmp_path_factory):
    """``(folder, command line, the two processes' stdouts)`` of the pump's
    diagnosis on two processes (its report in ``folder/two``)."""
    tmp = tmp_path_factory.mktemp("two_processes")
    data = _write_csv(tmp / "pump.csv", t_out_bias=0.5, units=6, steps=100)
    argv = [f"model={any_model.__file__}:PUMP", f"data={data}", "calibrate=wear"]
    port = free_port()
    commands = [
        [sys.executable, "-m", "jaxcal.diagnose", *argv, f"out={tmp / 'two'}",
         "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2",
         "--process-id", str(i)]
        for i in range(2)
    ]  # fmt: skip
    stdouts, errors = run_processes(commands)
    if errors:
        pytest.fail("\n\n".join(errors))
    return tmp, argv, stdouts


def test_static_report_equals_one_process(static_runs, capsys):
    tmp, argv, stdouts = static_runs
    assert main([*argv, f"out={tmp / 'one'}"]) == 0
    one_line = capsys.readouterr().out.strip().splitlines()[-1]
    one = json.loads((tmp / "one" / "report.json").read_text())
    two = json.loads((tmp / "two" / "report.json").read_text())
    assert one["verdict"] == "identified", one["ranking"][:3]
    assert one["data"]["rows"] == 600  # three chunks of 256 rows: split 2 + 1
    assert _comparable(two) == _comparable(one)
    # process 0 prints the verdict line of one process; process 1 writes nothing
    verdict = one_line.split("; report in")[0]
    assert stdouts[0].strip().splitlines()[-1].startswith(verdict)
    assert "verdict" not in stdouts[1]
    assert sorted(os.listdir(tmp)) == ["one", "pump.csv", "two"]


def test_model_with_memory_report_equals_one_process(tmp_path):
    port = str(free_port())
    commands = [
        [sys.executable, WORKER, "stateful", str(tmp_path), port, str(i)]
        for i in range(2)
    ]
    _, errors = run_processes(commands)
    if errors:
        pytest.fail("\n\n".join(errors))
    import diagnose_worker

    one = json.loads(json.dumps(diagnose_worker.report()))  # JSON's floats, as read
    assert one["added"] == ["sensor_bias[load]"], one["added"]
    for i in range(2):  # every process holds the verdict, not only process 0
        got = json.loads((tmp_path / f"process{i}.json").read_text())
        assert got == one


def test_one_process_evaluates_everything_itself():
    calls = []

    def evaluate(start, stop):
        calls.append((start, stop))
        return (np.arange(start, stop) * 2.0, np.arange(start, stop) > 3)

    got = sharding.evaluate_split(evaluate, 700, 256)
    assert calls == [(0, 700)]
    np.testing.assert_array_equal(got[0], np.arange(700) * 2.0)
    assert got[1].dtype == bool and got[1].sum() == 696


def test_cluster_flags_of_the_command_line():
    argv = ["data=a.csv", "calibrate=wear", "--coordinator", "127.0.0.1:4000",
            "--num-processes", "2", "--process-id", "1"]  # fmt: skip
    cfg, cluster = parse_args(argv)
    assert cfg.calibrate == ("wear",)
    assert cluster == {
        "coordinator": "127.0.0.1:4000",
        "num_processes": 2,
        "process_id": 1,
        "local_device_count": None,
    }
    with pytest.raises(ValueError, match="coordinator must be 'host:port'"):
        parse_args(["data=a.csv", "--num-processes", "2"])
    with pytest.raises(ValueError, match="unknown flag '--procs'"):
        parse_args(["data=a.csv", "--procs", "2"])
