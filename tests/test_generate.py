"""The data-set generation CLI: argument errors and a tiny end-to-end run."""

import json
import os
import subprocess
import sys

import h5py
import pytest

from jaxcal.cli.generate import main, parse_args
from jaxcal.models.turbofan.data.chunked_engine import jit_evaluate_engine
from jaxcal.models.turbofan.data.ncmapss_io import load_ncmapss
from jaxcal.runs.atomic import host_tag

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def evaluate():
    """The process-wide jitted engine call the CLI uses (compiled once per module)."""
    return jit_evaluate_engine


def test_overrides_and_default_output_path():
    cfg, out = parse_args(["dataset=agtf30", "seed=4", "dataset.num_scenarios=12"])
    assert (cfg.name, cfg.seed, cfg.num_scenarios) == ("agtf30", 4, 12)
    assert out == os.path.join("data", "agtf30.h5")
    _, out = parse_args(["out=x/y.h5", "dataset=tiny"])
    assert out == "x/y.h5"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["dataset=tiny", "bogus=1"], "unknown key 'bogus'; valid keys"),
        (["dataset=nope"], "unknown dataset 'nope'"),
        (["seed=1"], "missing"),
        (["dataset=tiny", "seed"], "expected key=value"),
        (["dataset=tiny", "seed=abc"], "seed='abc': expected an integer"),
        (["dataset=tiny", "dev_units=9"], "DatasetConfig.dev_units"),
    ],
)
def test_bad_arguments_exit_2_with_a_clear_message(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "usage:" in err


def test_unknown_key_lists_the_valid_keys(capsys):
    assert main(["dataset=tiny", "num_unit=3"]) == 2
    err = capsys.readouterr().err
    for key in ("num_units", "seed", "dt_s", "sensor_snr_db", "chunk_size", "out"):
        assert key in err


def test_unwritable_out_exits_2_before_any_work(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    bad = {
        "": "out='': expected a file path",
        str(tmp_path): "is a folder; expected a file path",
        str(blocker / "x.h5"): "is a file, so nothing can be created under it",
    }
    for out, message in bad.items():
        assert main(["dataset=tiny", f"out={out}"]) == 2, out
        err = capsys.readouterr().err
        assert message in err and "usage:" in err, out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_module_entry_point_exits_2_on_bad_out(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "jaxcal.generate", "dataset=tiny", f"out={tmp_path}"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "is a folder" in proc.stderr and "Traceback" not in proc.stderr


def test_module_entry_point_exits_2_on_unknown_key():
    proc = subprocess.run(
        [sys.executable, "-m", "jaxcal.generate", "dataset=tiny", "bogus=1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "valid keys" in proc.stderr


def test_cli_writes_a_readable_file(tmp_path, capsys, evaluate):
    del evaluate  # main() uses the same shared jitted engine
    out = tmp_path / "sub" / "tiny.h5"
    # the temp file of an earlier run killed mid-way (its pid is gone) is removed
    out.parent.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    stale = out.parent / f".tiny.h5.{host_tag()}.{proc.pid}.abcdefgh.tmp"
    stale.write_bytes(b"partial")
    assert main(["dataset=tiny", f"out={out}", "seed=3", "sensor_snr_db=70"]) == 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["tiny.h5"]
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("wrote ") and last.endswith("samples/s")
    dev = load_ncmapss(out, "dev")
    assert dev.num_rows > 0 and tuple(dev.units) == (1, 2)
    with h5py.File(out, "r") as f:
        config = json.loads(f.attrs["config"])
    assert config["seed"] == 3 and config["sensor_snr_db"] == 70.0
    assert f"rows (dev {dev.num_rows:,}" in last
