"""The diagnose CLI: argument errors exit 2; fabricated C-MAPSS / N-CMAPSS files."""

import dataclasses
import json
import os

import jax
import numpy as np
import pytest

from jaxcal.cli.diagnose import main
from jaxcal.diagnosis.data.synthetic import SyntheticConfig, make_synthetic_data
from jaxcal.diagnosis.kinds.linearization import linearize
from jaxcal.models import load
from jaxcal.models.turbofan.data.cmapss_text import SENSOR_MAP
from jaxcal.models.turbofan.data.ncmapss_io import write_ncmapss
from jaxcal.models.turbofan.data.record import Record
from jaxcal.models.turbofan.physics.constants import (
    MEASURED_SENSOR_NAMES,
    VIRTUAL_SENSOR_NAMES,
)
from jaxcal.models.turbofan.physics.reference import FD002_CONDITIONS
from jaxcal.models.turbofan.scenario import EFFECT_SIZES, ScenarioConfig, make_scenario


def _t2_offset_record(engine, size):
    """A small turbofan fleet with a T2 offset, as an N-CMAPSS Record (all sensors)."""
    cfg = SyntheticConfig(
        sensors=MEASURED_SENSOR_NAMES + VIRTUAL_SENSOR_NAMES,
        declared=("HPT_eff_mod",),
        sizes=EFFECT_SIZES,
        parameter_physical=True,
    )
    fleet = ScenarioConfig(num_units=2, rows_per_cycle=2, cycle_stride=2)
    syn = make_synthetic_data(
        jax.random.key(3), engine, "t2_offset", cfg, make_scenario(fleet), size=size
    )
    d = syn.data
    n = d.num_rows
    return Record(
        w=d.w, x=d.x, x_names=d.output_names, theta=d.theta, unit=d.unit,
        cycle=d.time.astype(int), flight_class=np.ones(n), hs=np.ones(n),
        rul=np.zeros(n, int),
    )  # fmt: skip


def test_unknown_key_exits_2_and_lists_valid_keys(capsys):
    assert main(["data=x.txt", "calibrate=HPC_eff_mod", "colour=red"]) == 2
    err = capsys.readouterr().err
    assert "unknown key 'colour'" in err and "calibrate" in err and "max_rows" in err


def test_missing_arguments_and_bad_names_exit_2(tmp_path, capsys):
    assert main(["calibrate=HPC_eff_mod"]) == 2
    assert "data=" in capsys.readouterr().err
    assert main([f"data={tmp_path / 'missing.txt'}", "calibrate=HPC_eff_mod"]) == 2
    assert "file not found" in capsys.readouterr().err
    path = tmp_path / "x.xyz"
    path.write_text("1\n")
    assert main([f"data={path}", "calibrate=HPC_eff_mod"]) == 2
    assert ".txt" in capsys.readouterr().err
    path = tmp_path / "x.csv"  # a table must name the model's columns
    path.write_text("1\n")
    assert main([f"data={path}", "calibrate=HPC_eff_mod"]) == 2
    assert "missing conditions ['alt', 'Mach', 'TRA', 'T2']" in capsys.readouterr().err
    assert main([f"data={path}", "calibrate=HPC_erosion"]) == 2
    assert "HPC_erosion" in capsys.readouterr().err


def test_unwritable_out_exits_2_before_the_data_is_read(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    data = tmp_path / "not_read_yet.txt"  # missing: the out check comes first
    for out, message in (
        (blocker, "is a file; expected a folder path"),
        (blocker / "sub", "is a file, so nothing can be created under it"),
    ):
        argv = [f"data={data}", "calibrate=HPC_eff_mod", f"out={out}"]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"out={str(out)!r}" in err and message in err


def _write_cmapss(path, engine, rng, t30_bias):
    """Two units x 36 cycles over the six FD002 conditions, HPC degrading linearly."""
    rows = []
    for unit in (1, 2):
        cond = np.tile(np.arange(6), 6)
        rng.shuffle(cond)
        cycle = np.arange(1, cond.size + 1)
        w = FD002_CONDITIONS[cond].copy()
        theta = np.zeros((cond.size, 10))
        theta[:, 4] = -0.01 * cycle / cycle.size
        theta[:, 5] = -0.02 * cycle / cycle.size
        y = linearize(engine, w, theta).x
        names = list(engine.output_names)
        cols = {s: y[:, names.index(n)] for s, n in SENSOR_MAP.items()}
        cols[3] = cols[3] + t30_bias
        for s, col in cols.items():
            if s not in (
                5,
                8,
                13,
                16,
                18,
                19,
            ):  # settings and rounded outputs stay clean
                cols[s] = col * (1.0 + 0.001 * rng.normal(size=col.size))
        cols.update(
            {
                1: w[:, 3],
                11: np.full(cond.size, 47.5),
                12: np.full(cond.size, 521.0),
                17: np.full(cond.size, 392.0),
            }
        )
        for i in range(cond.size):
            ops = [w[i, 0] / 1000.0, w[i, 1], w[i, 2]]
            vals = [cols[s][i] for s in range(1, 22)]
            rows.append(
                " ".join([str(unit), str(cycle[i])] + [f"{v:.4f}" for v in ops + vals])
                + "  "
            )
    path.write_text("\n".join(rows) + "\n")


@pytest.fixture(scope="module")
def engine():
    return load("cmapss")


@pytest.fixture(scope="module")
def t2_record(engine):
    """``_t2_offset_record(engine, 2.0)``, built once for the two N-CMAPSS tests (each
    writes its own file from it and leaves it unchanged)."""
    return _t2_offset_record(engine, 2.0)


def test_cli_writes_report_and_finds_a_t30_offset(tmp_path, engine, capsys):
    data = tmp_path / "train_FAKE.txt"
    _write_cmapss(data, engine, np.random.default_rng(0), t30_bias=25.0)
    out = tmp_path / "out"
    code = main(
        [
            f"data={data}",
            "engine=cmapss",
            "calibrate=HPC_eff_mod,HPC_flow_mod",
            f"out={out}",
            "families=sensor_bias,sensor_gain,effect",
        ]
    )
    assert code == 0, capsys.readouterr().err
    assert "verdict:" in capsys.readouterr().out
    for name in (
        "report.md",
        "report.json",
        "residuals.png",
        "signature.png",
        "theta.png",
    ):
        assert os.path.getsize(out / name) > 0, name
    rep = json.loads((out / "report.json").read_text())
    assert (
        "Nf" in rep["data"]["excluded"] and rep["data"]["noise_source"] == "estimated"
    )
    top = rep["ranking"][0]["name"]
    assert top in ("sensor_bias[T30]", "sensor_gain[T30]")
    assert rep["verdict"] in ("identified", "confounded")
    assert rep["identified"][0]["name"] == top
    b, a = rep["before"], rep["after"]
    assert a["tracking_rmse"]["T30"] < 0.5 * b["tracking_rmse"]["T30"]
    assert "## Before / after" in (out / "report.md").read_text()


def test_cli_on_an_ncmapss_file_finds_an_inlet_temperature_offset(tmp_path, t2_record):
    record = t2_record
    path = tmp_path / "N-CMAPSS_fake.h5"
    write_ncmapss(path, record, record)
    out = tmp_path / "out"
    assert main([f"data={path}", "calibrate=HPT_eff_mod", f"out={out}"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["data"]["sensors"]) <= set(MEASURED_SENSOR_NAMES)
    assert rep["verdict"] == "identified"
    assert rep["identified"][0]["name"] == "t2_offset"
    assert rep["identified"][0]["size"] == pytest.approx(2.0, rel=0.1)


def test_cli_drops_nan_rows_and_says_so(tmp_path, t2_record, capsys):
    record = t2_record
    x = record.x.copy()
    x[10:17, record.x_names.index("T30")] = np.nan  # a sensor drop-out
    x[40, record.x_names.index("P50")] = np.inf
    path = tmp_path / "N-CMAPSS_nan.h5"
    write_ncmapss(path, dataclasses.replace(record, x=x), record)
    out = tmp_path / "out"
    assert main([f"data={path}", "calibrate=HPT_eff_mod", f"out={out}"]) == 0
    said = "Dropped 8 rows with NaN or Inf values before the fit (rows per column: "
    assert said + "T30: 7, P50: 1)" in capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    assert rep["data"]["dropped"] == {"rows": 8, "columns": {"T30": 7, "P50": 1}}
    assert rep["data"]["rows"] == len(record) - 8
    assert said in (out / "report.md").read_text()
