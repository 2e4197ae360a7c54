"""``python -m jaxcal.prognose`` and its report, without the pipeline's calibration:
light help, bad arguments named (exit code 2), the files ``write_prognosis`` writes for
a toy fleet with a known end of life, and the command line end to end with the
pipeline replaced by that toy fleet's prognosis."""

import dataclasses
import inspect
import json
import os
import subprocess
import sys
import types

import numpy as np
import pytest
from support.prognosis_toy import prognosis

from jaxcal.cli.prognose import main, parse_args, parse_boundary
from jaxcal.models.turbofan.model import PROGNOSIS_THETA
from jaxcal.prognosis.report import CSV_COLUMNS, write_prognosis

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
REPORT_KEYS = {
    "config", "sources", "coverage", "samples", "training_units", "test_units",
    "model", "noise_check", "timings", "notes", "units", "figures",
}  # fmt: skip
ROW_KEYS = {"unit", "now", "rul", "low", "high", "driver", "driver_share", "censored"}


@pytest.fixture(scope="module")
def toy():
    """The toy fleet's prognosis (8 training, 8 test units) and the true RULs."""
    return prognosis(num_train=8, num_test=8, samples=200)


@pytest.fixture
def files(tmp_path):
    """Existing train / test / truth files (their content is not read here)."""
    paths = {"train": "train.csv", "test": "test.csv", "truth": "truth.txt"}
    for name in paths.values():
        (tmp_path / name).write_text("0\n")
    return {k: str(tmp_path / v) for k, v in paths.items()}


def test_help_prints_the_usage_without_importing_jax():
    code = (
        "import sys; from jaxcal.cli.prognose import main; "
        "assert main(['--help']) == 0; "
        "heavy = [m for m in ('jax', 'matplotlib', 'numpy') if m in sys.modules]; "
        "assert not heavy, heavy"
    )
    env = {**os.environ, "PYTHONPATH": ROOT}
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr
    assert (
        "usage: python -m jaxcal.prognose train=FILE test=FILE out=DIR" in done.stdout
    )


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["test={test}", "out={out}"], "train=<file> is required"),
        (["train=missing.txt", "test={test}", "out={out}"], "train='missing.txt'"),
        (["train={train}", "test={test}"], "out=<folder> is required"),
        (
            ["train={train}", "test={test}", "out={out}", "truth=no.txt"],
            "truth=",
        ),
        (
            ["train={train}", "test={test}", "out={out}", "boundary=a"],
            "boundary=",
        ),
        (
            ["train={train}", "test={test}", "out={out}", "boundary=a:x"],
            "boundary",
        ),
        (
            ["train={train}", "test={test}", "out={out}", "coverage=1.5"],
            "coverage",
        ),
        (["train={train}", "test={test}", "out={out}", "samples=x"], "samples"),
        (["train={train}", "test={test}", "out={out}", "sede=1"], "'sede'"),
        (["train={truth}", "test={test}", "out={train}"], "out="),
    ],
)
def test_bad_arguments_exit_2_naming_the_field(args, named, files, tmp_path, capsys):
    argv = [a.format(**files, out=tmp_path / "out") for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert named in err, err


def test_boundary_is_parsed_by_name():
    assert parse_boundary(["HPC_eff_mod:-0.05", " fouling : 2e-4"]) == {
        "HPC_eff_mod": -0.05,
        "fouling": 2e-4,
    }
    with pytest.raises(ValueError, match="given twice"):
        parse_boundary(["a:1", "a:2"])


def test_settings_default_to_the_turbofan_and_take_every_field(files, tmp_path):
    cfg = parse_args([f"train={files['train']}", f"test={files['test']}",
                      f"out={tmp_path}", "noise_scale=none", "seed=3"])  # fmt: skip
    assert cfg.model_spec == "cmapss" and cfg.noise_scale is None and cfg.seed == 3
    cfg = parse_args([f"train={files['train']}", f"test={files['test']}",
                      f"out={tmp_path}", "model=heat_exchanger"])  # fmt: skip
    assert cfg.model_spec == "heat_exchanger"


def test_turbofan_defaults_name_its_parameters_and_outputs():
    from jaxcal.models import load
    from jaxcal.models.turbofan.model import PROGNOSIS_OUTPUTS

    model = load("cmapss")
    model.parameter_index(PROGNOSIS_THETA)
    assert set(PROGNOSIS_OUTPUTS) <= set(model.output_names)


def test_report_files_of_a_toy_fleet(toy, tmp_path):
    result, truth = toy
    out = tmp_path / "report"
    rep = write_prognosis(str(out), result, truth=truth, source={"test": "toy"})
    lines = (out / "rul.csv").read_text().splitlines()
    assert lines[0] == ",".join(CSV_COLUMNS) == "unit,rul,rul_low,rul_high"
    assert len(lines) == 1 + truth.size
    table = np.loadtxt(out / "rul.csv", delimiter=",", skiprows=1)
    assert (table[:, 2] <= table[:, 1]).all() and (table[:, 1] <= table[:, 3]).all()
    stored = json.loads((out / "report.json").read_text())
    assert REPORT_KEYS | {"score"} <= set(stored)
    assert stored["model"] == json.loads(json.dumps(result.model.to_json()))
    assert set(stored["units"][0]) == ROW_KEYS | {"truth", "error"}
    assert stored["score"]["units"] == truth.size
    assert stored["score"]["rmse"] < 5.0  # the toy's end of life is learnable
    for unit in result.prediction.unit:
        assert (out / "units" / f"unit_{unit}.png").stat().st_size > 0
    assert (out / "rul.png").is_file()
    page = (out / "report.md").read_text()
    assert "## Score against the truth" in page and "units/unit_1.png" in page
    assert rep["out"] == str(out)


def test_report_without_truth_has_no_score(toy, tmp_path):
    result, _ = toy
    rep = write_prognosis(str(tmp_path), result, config={"seed": 0})
    assert "score" not in rep and "truth" not in rep["units"][0]
    assert (tmp_path / "rul.png").is_file()
    assert "Score" not in (tmp_path / "report.md").read_text()


def _fake_pipeline(result):
    """A stand-in for ``jaxcal.prognosis.pipeline`` that returns ``result``."""

    @dataclasses.dataclass(frozen=True)
    class PrognosisConfig:
        method: str = "ukf"
        coverage: float = 0.9
        samples: int = 1000
        trend: str | None = None
        max_tightness: float = 0.35
        noise_scale: float | None = None
        folds: int = 5
        seed: int = 0

    calls = []

    def prognose(model, train, test, theta=None, noise=None, boundary=None,
                 config=PrognosisConfig(), *, outputs=None, progress=True):  # fmt: skip
        calls.append({"theta": theta, "outputs": outputs, "boundary": boundary})
        return result

    module = types.ModuleType("jaxcal.prognosis.pipeline")
    module.PrognosisConfig, module.prognose, module.calls = (
        PrognosisConfig,
        prognose,
        calls,
    )
    return module


def test_command_line_end_to_end_with_a_stand_in_pipeline(
    toy, files, tmp_path, monkeypatch, capsys
):
    result, truth = toy
    np.savetxt(files["truth"], truth, fmt="%d")
    fake = _fake_pipeline(result)
    monkeypatch.setitem(sys.modules, "jaxcal.prognosis.pipeline", fake)
    out = tmp_path / "out"
    argv = [f"train={files['train']}", f"test={files['test']}", f"out={out}",
            f"truth={files['truth']}", "boundary=HPC_eff_mod:-0.05"]  # fmt: skip
    assert main(argv) == 0
    said = capsys.readouterr().out
    assert "8 test units, RMSE" in said and str(out) in said
    assert fake.calls[0]["theta"] == list(PROGNOSIS_THETA)  # the defaults
    assert fake.calls[0]["outputs"][:2] == ["T24", "T30"]
    assert fake.calls[0]["boundary"] == {"HPC_eff_mod": -0.05}
    stored = json.loads((out / "report.json").read_text())
    assert stored["sources"]["truth"] == files["truth"]
    assert stored["config"]["prognosis"]["seed"] == 0


def test_a_bad_truth_file_fails_before_the_calibration(
    toy, files, tmp_path, monkeypatch, capsys
):
    result, _ = toy
    with open(files["truth"], "w") as handle:
        handle.write("12\nabc\n")
    fake = _fake_pipeline(result)
    monkeypatch.setitem(sys.modules, "jaxcal.prognosis.pipeline", fake)
    argv = [f"train={files['train']}", f"test={files['test']}",
            f"out={tmp_path / 'out'}", f"truth={files['truth']}"]  # fmt: skip
    assert main(argv) == 2
    assert "line 2: 'abc' is not a number" in capsys.readouterr().err
    assert fake.calls == []  # nothing calibrated


def test_the_real_pipeline_takes_what_the_command_line_passes():
    pipeline = pytest.importorskip("jaxcal.prognosis.pipeline")
    fields = {f.name for f in dataclasses.fields(pipeline.PrognosisConfig)}
    assert fields >= set(
        inspect.signature(_fake_pipeline(None).PrognosisConfig).parameters
    )
    params = inspect.signature(pipeline.prognose).parameters
    assert {"theta", "noise", "boundary", "config", "outputs"} <= set(params)
