"""The run's data reader: NaN rows and renamed columns refused by default, with the
``dataset.nonfinite=drop`` and ``dataset.rename`` overrides (train exits 2 naming the
file, column and rows)."""

import dataclasses

import h5py
import numpy as np
import pytest

from jaxcal.cli.train import main
from jaxcal.models.turbofan.data.ncmapss_io import write_ncmapss
from jaxcal.models.turbofan.data.record import Record
from jaxcal.models.turbofan.physics.constants import (
    MEASURED_SENSOR_NAMES,
    VIRTUAL_SENSOR_NAMES,
)
from jaxcal.models.turbofan.training import load_calibration_data
from jaxcal.training.config import resolve_config
from jaxcal.training.data.run import read_options

SENSORS = MEASURED_SENSOR_NAMES + VIRTUAL_SENSOR_NAMES


def _record(units, length, seed) -> Record:
    rng = np.random.default_rng(seed)
    n = len(units) * length
    cycle = np.tile(1 + np.arange(length) // 4, len(units))
    return Record(
        w=rng.normal(size=(n, 4)) * [1e4, 0.1, 10, 20] + [2e4, 0.5, 60, 480],
        x=rng.normal(size=(n, 28)) * 10 + 500,
        x_names=SENSORS,
        theta=rng.normal(size=(n, 10)) * 1e-3,
        unit=np.repeat(units, length),
        cycle=cycle,
        flight_class=np.ones(n),
        hs=np.ones(n),
        rul=cycle.max() - cycle,
    )


@pytest.fixture
def nan_file(tmp_path):
    """Dev units 1-3 (12 rows each) with NaN T30 on dev rows 14-16, test units 4-5."""
    dev, test = _record([1, 2, 3], 12, 0), _record([4, 5], 12, 1)
    x = dev.x.copy()
    x[14:17, SENSORS.index("T30")] = np.nan
    path = tmp_path / "user.h5"
    write_ncmapss(path, dataclasses.replace(dev, x=x), test)
    return path


def test_nan_rows_refused_by_default_and_dropped_on_request(nan_file):
    with pytest.raises(ValueError) as err:
        load_calibration_data(str(nan_file))
    msg = str(err.value)
    assert "user.h5 [dev]" in msg and "column T30: 3 rows (rows 14, 15, 16)" in msg
    logged = []
    data = load_calibration_data(str(nan_file), nonfinite="drop", log=logged.append)
    assert data.info["dropped"] == {
        "dev": {"rows": 3, "columns": {"T30": 3}},
        "test": {"rows": 0, "columns": {}},
    }
    assert data.info["rows"]["dev"] == 33
    assert len(logged) == 1
    assert "dev: 3 rows with NaN / Inf dropped (T30 3)" in logged[0]
    assert np.isfinite(data.train.x).all()


def test_dataset_options_parse_and_reach_the_reader(nan_file):
    cfg = resolve_config(
        ["dataset=ncmapss", f"path={nan_file}", "dataset.nonfinite=drop",
         "dataset.rename=T_24:T24,T_30:T30"]
    )  # fmt: skip
    assert read_options(cfg.dataset) == {
        "nonfinite": "drop",
        "rename": {"T_24": "T24", "T_30": "T30"},
    }
    with pytest.raises(ValueError, match="dataset.nonfinite.*error, drop"):
        resolve_config(["dataset.nonfinite=maybe"])
    with pytest.raises(ValueError, match="dataset.rename must be"):
        resolve_config(["dataset.rename=T_24"])


def test_renamed_columns_refused_then_mapped(nan_file):
    with h5py.File(nan_file, "a") as f:
        names = [v.decode() for v in f["X_s_var"][()]]
        del f["X_s_var"]
        f["X_s_var"] = np.array(["T_24" if n == "T24" else n for n in names], "S")
    with pytest.raises(ValueError, match="X_s_var: unknown \\['T_24'\\], missing"):
        load_calibration_data(str(nan_file), nonfinite="drop")
    data = load_calibration_data(
        str(nan_file), nonfinite="drop", rename={"T_24": "T24"}
    )
    assert data.problem.output_names == MEASURED_SENSOR_NAMES


def test_train_cli_exits_2_naming_file_column_and_rows(nan_file, tmp_path, capsys):
    runs = tmp_path / "runs"
    argv = ["dataset=ncmapss", f"path={nan_file}", "preset=smoke", "dataset.stride=1",
            f"output.runs_dir={runs}", "output.progress=false"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "user.h5 [dev]" in err and "column T30: 3 rows (rows 14, 15, 16)" in err
    assert "dataset.nonfinite=drop" in err
    assert not runs.exists() or not any(runs.rglob("*"))  # nothing blocks a rerun
