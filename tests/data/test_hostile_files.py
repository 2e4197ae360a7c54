"""Files as a careless user or a faulty pipeline gives them (issue 42): a CSV saved
in a European locale, unit ids beyond int64, a result file whose stored dtypes were
edited, a policy checkpoint cut short, and output paths that cannot be written.
Each is read correctly or is an error naming the file, field or rows, raised
before any work."""

import json
import os

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.calibrators.front.result import META_KEY, CalibrationResult
from jaxcal.cli.fleet import parse_args as parse_fleet
from jaxcal.data.readers import read_dataset
from jaxcal.fleet.results import FleetResultWriter
from jaxcal.runs.checkpoint import Checkpointer


def _frame():
    return pd.DataFrame(
        {
            "unit": [1, 1, 1, 2, 2],
            "time": [0, 1, 2, 0, 1],
            "a": [1.5, 2.25, -0.5, 3.0, 1e-3],
            "b": [10.0, 11.5, 12.0, 13.0, 14.0],
            "y1": [0.1, 0.2, 0.3, 0.4, 0.5],
            "y2": [20.0, 21.0, 22.0, 23.0, 24.0],
            "split": ["train", "train", "train", "test", "test"],
        }
    )


def test_a_semicolon_csv_with_decimal_commas_reads_as_the_same_numbers(model, tmp_path):
    frame = _frame()
    plain = tmp_path / "plain.csv"
    european = tmp_path / "european.csv"
    frame.to_csv(plain, index=False)
    frame.to_csv(european, index=False, sep=";", decimal=",")
    assert "1,5" in european.read_text()  # the file as a European locale saves it
    ref, got = read_dataset(plain, model), read_dataset(european, model)
    np.testing.assert_array_equal(got.w, ref.w)
    np.testing.assert_array_equal(got.x, ref.x)
    np.testing.assert_array_equal(got.unit, ref.unit)
    assert got.split.tolist() == ref.split.tolist()


def test_a_csv_mixing_decimal_marks_or_separators_is_named(model, tmp_path):
    mixed = tmp_path / "mixed.csv"
    mixed.write_text("unit;time;a;b;y1;y2\n1;0;1,5;2;3;4\n1;1;2.5;2;3;4\n")
    with pytest.raises(ValueError, match=r"mixed.csv: column 'a' mixes decimal"):
        read_dataset(mixed, model)
    both = tmp_path / "both.csv"
    both.write_text("unit;time,a;b,y1;y2\n1;0,1;2,3;4\n")
    with pytest.raises(ValueError, match=r"both.csv: the header line holds both"):
        read_dataset(both, model)


@pytest.mark.parametrize("first", [2**63, 2**64 + 1])
def test_unit_ids_beyond_int64_are_named_not_merged(model, tmp_path, first):
    path = tmp_path / "big_units.csv"
    rows = [f"{first + k},0,1,2,3,4" for k in range(3)]
    path.write_text("unit,time,a,b,y1,y2\n" + "\n".join(rows) + "\n")
    with pytest.raises(
        ValueError, match=r"big_units.csv: column 'unit'.*rows: 2, 3, 4"
    ):
        read_dataset(path, model)
    # ids that int64 holds are read as they are
    path.write_text("unit,time,a,b,y1,y2\n" + "\n".join(
        f"{2**62 + k},0,1,2,3,4" for k in range(3)) + "\n")  # fmt: skip
    assert len(np.unique(read_dataset(path, model).unit)) == 3


def _saved_result(model, tmp_path):
    frame = _frame().drop(columns="split")
    result = jaxcal.calibrate(model, frame, "ukf", noise={"y1": 0.1, "y2": 0.1},
                              progress=False)  # fmt: skip
    return result, result.save(tmp_path / "result.parquet")


def _tamper(path, edit):
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    meta = json.loads(table.schema.metadata[META_KEY])
    edit(meta)
    table = table.replace_schema_metadata({META_KEY: json.dumps(meta).encode()})
    pq.write_table(table, path)


def test_a_result_file_with_edited_dtypes_or_columns_is_refused(model, tmp_path):
    result, path = _saved_result(model, tmp_path)
    loaded = CalibrationResult.load(path)
    np.testing.assert_array_equal(loaded.theta, result.theta)
    _tamper(path, lambda m: m["dtypes"].update(theta="int8"))
    with pytest.raises(ValueError, match=r"result.parquet: field 'theta' .*'int8'"):
        CalibrationResult.load(path)
    _, path = _saved_result(model, tmp_path)
    _tamper(path, lambda m: m["dtypes"].update(valid="float64"))
    with pytest.raises(ValueError, match=r"field 'valid' .*booleans"):
        CalibrationResult.load(path)
    _, path = _saved_result(model, tmp_path)
    _tamper(path, lambda m: m.update(theta_names=["p", "extra"]))
    with pytest.raises(ValueError, match=r"field 'theta' has 1 columns for the 2"):
        CalibrationResult.load(path)


def test_a_truncated_checkpoint_names_its_folder_and_file(tmp_path):
    tree = {"w": jnp.arange(4000.0), "b": jnp.ones(3)}
    with Checkpointer(tmp_path / "run" / "policy") as ckpt:
        ckpt.save(0, tree, wait=True)
    files = [p for p in (tmp_path / "run" / "policy" / "0").rglob("*") if p.is_file()]
    biggest = max(files, key=lambda p: p.stat().st_size)
    data = biggest.read_bytes()
    biggest.write_bytes(data[: len(data) // 2])
    with Checkpointer(tmp_path / "run" / "policy") as ckpt:
        with pytest.raises(ValueError, match=r"run/policy/0.*truncated or corrupt"):
            ckpt.restore(None, tree)


def _targets(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    return {
        "under a file": (str(a_file / "out.h5"), "is a file"),
        "a folder": (str(tmp_path), "is a folder"),
    }


def test_output_paths_that_cannot_be_written_are_refused_before_any_work(
    model, tmp_path
):
    for path, words in _targets(tmp_path).values():
        with pytest.raises(ValueError, match=f"out=.*{words}"):
            parse_fleet([f"data={tmp_path / 'd.csv'}", f"out={path}", "method=ukf",
                         "model=heat_exchanger"])  # fmt: skip
        with pytest.raises(ValueError, match=f"path=.*{words}"):
            FleetResultWriter(path, theta_names=("p",), sensor_names=("y1",))
    result, _ = _saved_result(model, tmp_path)
    for path, words in _targets(tmp_path).values():
        with pytest.raises(ValueError, match=f"path=.*{words}"):
            result.save(path)
    # a missing folder is created, as the check says
    deep = tmp_path / "new" / "deeper" / "out.h5"
    with FleetResultWriter(deep, theta_names=("p",), sensor_names=("y1",)):
        pass
    assert os.path.isfile(deep)


def test_a_model_spec_string_is_an_error_that_says_how_to_load_it(model, tmp_path):
    path = tmp_path / "plain.csv"
    _frame().to_csv(path, index=False)
    with pytest.raises(ValueError, match=r"model: got str 'cmapss'.*models\.load"):
        read_dataset(path, "cmapss")
    with pytest.raises(ValueError, match="model: got int 3; read_dataset needs"):
        read_dataset(path, 3)
    assert read_dataset(path, model).num_rows == 5
