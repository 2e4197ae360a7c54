"""The data-set generation CLI: argument errors and a tiny end-to-end run."""

import json
import os
import subprocess
import sys

import h5py
import pytest

from jaxcal.data.chunked_engine import jit_evaluate_engine
from jaxcal.data.ncmapss_io import load_ncmapss
from jaxcal.generate import main, parse_args

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
    assert main(["dataset=tiny", f"out={out}", "seed=3", "sensor_snr_db=70"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("wrote ") and last.endswith("samples/s")
    dev = load_ncmapss(out, "dev")
    assert dev.num_rows > 0 and tuple(dev.units) == (1, 2)
    with h5py.File(out, "r") as f:
        config = json.loads(f.attrs["config"])
    assert config["seed"] == 3 and config["sensor_snr_db"] == 70.0
    assert f"rows (dev {dev.num_rows:,}" in last
