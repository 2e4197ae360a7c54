"""Record container and N-CMAPSS HDF5 reader / writers."""

import dataclasses
import hashlib
import json

import h5py
import numpy as np
import pytest

from jaxcal.models.turbofan.data.ncmapss_io import (
    NCMAPSSWriter,
    load_ncmapss,
    ncmapss_info,
    write_ncmapss,
)
from jaxcal.models.turbofan.data.record import Record
from jaxcal.models.turbofan.physics.constants import (
    AUX_NAMES,
    CONDITION_NAMES,
    HEALTH_NAMES,
    MEASURED_SENSOR_NAMES,
    VIRTUAL_SENSOR_NAMES,
)

NCMAPSS_SENSORS = MEASURED_SENSOR_NAMES + VIRTUAL_SENSOR_NAMES


def make_record(units, lengths, seed=0, rate=1.0) -> Record:
    """A fabricated record: unit u has lengths[i] rows over 3 cycles, all 28 sensors."""
    rng = np.random.default_rng(seed)
    unit = np.concatenate([np.full(n, u) for u, n in zip(units, lengths, strict=True)])
    cycle = np.concatenate([1 + np.arange(n) * 3 // n for n in lengths])
    n = len(unit)
    fc = np.concatenate(
        [np.full(k, 1 + u % 3, float) for u, k in zip(units, lengths, strict=True)]
    )
    return Record(
        w=rng.normal(size=(n, 4)) * [1e4, 0.1, 10, 20] + [2e4, 0.5, 60, 480],
        x=rng.normal(size=(n, 28)) * 10 + 500,
        x_names=NCMAPSS_SENSORS,
        theta=rng.normal(size=(n, 10)) * 1e-3,
        unit=unit,
        cycle=cycle,
        flight_class=fc,
        hs=(cycle < 3).astype(float),
        rul=3 - cycle,
        sample_rate_hz=rate,
        source="fabricated",
    )


def assert_records_equal(a: Record, b: Record):
    assert a.x_names == b.x_names
    for name in ("w", "x", "theta", "unit", "cycle", "flight_class", "hs", "rul"):
        va, vb = getattr(a, name), getattr(b, name)
        assert va.dtype == vb.dtype, name
        np.testing.assert_array_equal(va, vb, err_msg=name)
    assert a.sample_rate_hz == b.sample_rate_hz


def write_real_layout(path, dev: Record, test: Record, permute: bool):
    """Write with h5py directly, as NASA's files: real names / dtypes, no attrs.

    With ``permute`` every column group is stored in a scrambled order (names and data
    permuted together), which the reader must undo from the ``*_var`` arrays.
    """
    rng = np.random.default_rng(123)

    def perm(k):
        return rng.permutation(k) if permute else np.arange(k)

    orders = {g: perm(k) for g, k in (("W", 4), ("X_s", 14), ("X_v", 14), ("T", 10))}
    orders["A"] = perm(4)
    names = {
        "W": np.array(CONDITION_NAMES),
        "X_s": np.array(MEASURED_SENSOR_NAMES),
        "X_v": np.array(VIRTUAL_SENSOR_NAMES),
        "T": np.array(HEALTH_NAMES),
        "A": np.array(AUX_NAMES),
    }
    with h5py.File(path, "w") as f:
        for split, rec in (("dev", dev), ("test", test)):
            aux = np.stack([rec.unit, rec.cycle, rec.flight_class, rec.hs], 1)
            arrays = {
                "W": rec.w,
                "X_s": rec.columns(MEASURED_SENSOR_NAMES),
                "X_v": rec.columns(VIRTUAL_SENSOR_NAMES),
                "T": rec.theta,
                "A": aux.astype(np.float64),
            }
            for g, arr in arrays.items():
                f.create_dataset(f"{g}_{split}", data=arr[:, orders[g]])
            f.create_dataset(f"Y_{split}", data=rec.rul[:, None].astype(np.int64))
        for g, dtype in (("W", "|S4"), ("X_s", "|S4"), ("X_v", "|S5"), ("T", "|S12")):
            f.create_dataset(f"{g}_var", data=names[g][orders[g]].astype(dtype))
        f.create_dataset("A_var", data=names["A"][orders["A"]].astype("|S5"))


@pytest.fixture
def records():
    dev = make_record(units=[1, 2, 3], lengths=[7, 11, 5], seed=1)
    test = make_record(units=[4, 5], lengths=[6, 9], seed=2)
    return dev, test


# --------------------------------------------------------------------------- Record


def test_record_coerces_dtypes_and_selects(records):
    dev, _ = records
    assert dev.unit.dtype == np.int64 and dev.w.dtype == np.float64
    np.testing.assert_array_equal(dev.units, [1, 2, 3])
    sub = dev.select_units([3, 1])
    np.testing.assert_array_equal(sub.units, [1, 3])
    assert len(sub) == 12
    np.testing.assert_array_equal(
        dev.columns(["Nf", "T24"]),
        dev.x[:, [NCMAPSS_SENSORS.index("Nf"), NCMAPSS_SENSORS.index("T24")]],
    )


@pytest.mark.parametrize(
    "change, match",
    [
        ({"w": np.zeros((23, 3))}, "Record.w must have shape"),
        ({"x_names": NCMAPSS_SENSORS[:-1] + ("bogus",)}, "unknown sensor name"),
        ({"x_names": NCMAPSS_SENSORS[:-1] + ("T24",)}, "repeated names"),
        ({"theta": np.zeros((23, 9))}, "Record.theta must have shape"),
        ({"cycle": np.zeros(22, int)}, "Record.cycle must have shape"),
        ({"unit": np.full(23, 1.5)}, "Record.unit must hold integers"),
        ({"extras": {"a": np.zeros(5)}}, "extras\\['a'\\]"),
        ({"sample_rate_hz": -1.0}, "sample_rate_hz"),
    ],
)
def test_record_rejects_bad_shapes(records, change, match):
    dev, _ = records
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(dev, **change)


def test_record_errors_list_available_names(records):
    dev, _ = records
    with pytest.raises(ValueError, match="available columns are .*'T24'"):
        dev.columns(["T24", "nope"])
    with pytest.raises(ValueError, match="available units are \\[1, 2, 3\\]"):
        dev.select_units([9])


# --------------------------------------------------------------------------- HDF5


def test_write_read_round_trip_is_exact(tmp_path, records):
    dev, test = records
    path = tmp_path / "data.h5"
    write_ncmapss(path, dev, test, attrs={"config": {"seed": 3}, "note": "x"})
    for split, rec in (("dev", dev), ("test", test)):
        assert_records_equal(load_ncmapss(path, split), rec)
    with h5py.File(path, "r") as f:
        for g in ("W", "X_s", "X_v", "T", "A"):
            assert f[f"{g}_dev"].dtype == np.float64
        assert f["Y_dev"].dtype == np.int64 and f["Y_dev"].shape == (23, 1)
        dtypes = {g: f[f"{g}_var"].dtype.str for g in ("W", "X_s", "X_v", "T", "A")}
        assert dtypes == {
            "W": "|S4",
            "X_s": "|S4",
            "X_v": "|S5",
            "T": "|S12",
            "A": "|S5",
        }
        assert [v.decode() for v in f["X_s_var"][()]] == list(MEASURED_SENSOR_NAMES)
        assert f["X_s_dev"].chunks is None  # contiguous, as NASA's files
    info = ncmapss_info(path)
    assert info["splits"] == {
        "dev": {"rows": 23, "units": [1, 2, 3]},
        "test": {"rows": 15, "units": [4, 5]},
    }
    assert json.loads(info["attrs"]["config"]) == {"seed": 3}
    assert info["sample_rate_hz"] == 1.0
    assert info["columns"]["T"] == list(HEALTH_NAMES)


def test_writer_is_deterministic(tmp_path, records):
    dev, test = records
    digests = []
    for name in ("a.h5", "b.h5"):
        write_ncmapss(tmp_path / name, dev, test, attrs={"seed": 0})
        digests.append(hashlib.sha256((tmp_path / name).read_bytes()).hexdigest())
    assert digests[0] == digests[1]


@pytest.mark.parametrize("permute", [False, True])
def test_reads_nasa_layout_written_by_h5py(tmp_path, records, permute):
    dev, test = records
    path = tmp_path / "N-CMAPSS_DS01-005.h5"
    write_real_layout(path, dev, test, permute=permute)
    for split, rec in (("dev", dev), ("test", test)):
        assert_records_equal(load_ncmapss(path, split), rec)  # 1 Hz without attrs
    got = load_ncmapss(path, "dev", units=[2], sensors=["Wf", "T40", "T24"])
    np.testing.assert_array_equal(
        got.x, dev.select_units([2]).columns(["Wf", "T40", "T24"])
    )
    assert ncmapss_info(path)["attrs"] == {}


def test_unit_row_and_sensor_selection(tmp_path, records):
    dev, test = records
    path = tmp_path / "data.h5"
    write_ncmapss(path, dev, test)
    # Scan blocks of 4 rows so units straddle scan blocks and read blocks.
    got = load_ncmapss(path, "dev", units=[3, 1], block_rows=4)
    assert_records_equal(got, dev.select_units([1, 3]))
    got = load_ncmapss(path, "dev", sensors=["P30", "Nc"])
    assert got.x_names == ("P30", "Nc")
    np.testing.assert_array_equal(got.x, dev.columns(["P30", "Nc"]))
    got = load_ncmapss(path, "dev", rows=(3, 20), stride=3, block_rows=2)
    assert_records_equal(
        got, dataclasses.replace(dev.take(slice(3, 20, 3)), sample_rate_hz=1 / 3)
    )
    # A unit selection sees exactly the rows of the full strided load.
    full = load_ncmapss(path, "dev", rows=(1, 23), stride=4)
    part = load_ncmapss(path, "dev", units=[2], rows=(1, 23), stride=4, block_rows=3)
    assert_records_equal(part, full.select_units([2]))


def test_appender_equals_one_shot_writer(tmp_path, records):
    dev, test = records
    write_ncmapss(tmp_path / "one.h5", dev, test, attrs={"k": 1})
    with NCMAPSSWriter(tmp_path / "chunked.h5", attrs={"k": 1}, chunk_rows=4) as writer:
        for a, b in ((0, 5), (5, 6), (6, 23)):
            writer.append("dev", dev.take(slice(a, b)))
        writer.append("test", test.take(slice(0, 8)))
        writer.append("test", test.take(slice(8, 15)))
    with h5py.File(tmp_path / "one.h5") as f1, h5py.File(tmp_path / "chunked.h5") as f2:
        assert sorted(f1) == sorted(f2)
        for key in f1:
            assert f1[key].dtype == f2[key].dtype, key
            np.testing.assert_array_equal(f1[key][()], f2[key][()], err_msg=key)
        assert dict(f1.attrs) == dict(f2.attrs)


def test_writer_exception_leaves_no_file_and_keeps_old_one(tmp_path, records):
    dev, test = records
    path = tmp_path / "data.h5"
    with pytest.raises(RuntimeError, match="boom"):
        with NCMAPSSWriter(path) as writer:
            writer.append("dev", dev)
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []

    write_ncmapss(path, dev, test)
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="boom"):
        with NCMAPSSWriter(path) as writer:
            writer.append("dev", test)
            raise RuntimeError("boom")
    bad = dataclasses.replace(dev, x=dev.x[:, :-1], x_names=dev.x_names[:-1])
    with pytest.raises(ValueError, match="lacks sensor column.*'phi'"):
        write_ncmapss(path, bad, test)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["data.h5"]


def test_writer_rejects_unwritable_records(tmp_path, records):
    dev, test = records
    path = tmp_path / "data.h5"
    with pytest.raises(ValueError, match="theta=None"):
        write_ncmapss(path, dataclasses.replace(dev, theta=None), test)
    with pytest.raises(ValueError, match="sample_rate_hz"):
        write_ncmapss(path, dev, dataclasses.replace(test, sample_rate_hz=0.1))
    with pytest.raises(ValueError, match="split must be one of"):
        with NCMAPSSWriter(path) as writer:
            writer.append("train", dev)
    assert list(tmp_path.iterdir()) == []


def test_reader_errors_name_path_and_field(tmp_path, records):
    dev, test = records
    missing = tmp_path / "nope.h5"
    with pytest.raises(FileNotFoundError, match="nope.h5"):
        load_ncmapss(missing)
    path = tmp_path / "data.h5"
    write_ncmapss(path, dev, test)
    with pytest.raises(ValueError, match="split must be one of"):
        load_ncmapss(path, "train")
    with pytest.raises(ValueError, match="no unit\\(s\\) \\[9\\].*units there are"):
        load_ncmapss(path, "dev", units=[9])
    with pytest.raises(ValueError, match="sensor\\(s\\) \\['T99'\\]"):
        load_ncmapss(path, "dev", sensors=["T99"])
    with pytest.raises(ValueError, match="rows must be"):
        load_ncmapss(path, "dev", rows=(5, 100))
    with pytest.raises(ValueError, match="stride"):
        load_ncmapss(path, "dev", stride=0)
    with h5py.File(path, "a") as f:
        del f["X_v_test"]
    with pytest.raises(ValueError, match="data.h5: missing dataset 'X_v_test'"):
        load_ncmapss(path, "test")
    assert len(load_ncmapss(path, "dev")) == 23  # the dev split is still whole


def test_unit_selection_reads_only_unit_column_and_unit_rows(
    tmp_path, records, monkeypatch
):
    dev, test = records
    path = tmp_path / "data.h5"
    write_ncmapss(path, dev, test)
    reads = []
    original = h5py.Dataset.__getitem__

    def spy(self, args, *rest, **kw):
        reads.append((self.name.lstrip("/"), args))
        return original(self, args, *rest, **kw)

    monkeypatch.setattr(h5py.Dataset, "__getitem__", spy)
    got = load_ncmapss(path, "dev", units=[2], sensors=["Nf"], block_rows=8)
    monkeypatch.undo()
    assert_records_equal(
        got,
        dataclasses.replace(
            dev.select_units([2]),
            x=dev.select_units([2]).columns(["Nf"]),
            x_names=("Nf",),
        ),
    )
    unit_rows = range(7, 18)  # unit 2 occupies rows 7..17 of the dev split
    scans = [a for name, a in reads if name == "A_dev" and isinstance(a, tuple)]
    assert scans and all(a[1] == AUX_NAMES.index("unit") for a in scans)
    data_reads = [
        (n, a) for n, a in reads if n.endswith("_dev") and not isinstance(a, tuple)
    ]
    assert {n for n, _ in data_reads} == {"W_dev", "X_s_dev", "T_dev", "Y_dev", "A_dev"}
    for _, sl in data_reads:
        assert sl.start in unit_rows and sl.stop - 1 in unit_rows


# --------------------------------------------------------------- names and NaN policy


def _rename_columns(path, group, mapping):
    """Respell some ``<group>_var`` names in place, as a user's file might."""
    with h5py.File(path, "a") as f:
        names = [v.decode() for v in f[f"{group}_var"][()]]
        del f[f"{group}_var"]
        f.create_dataset(
            f"{group}_var", data=np.array([mapping.get(n, n) for n in names], "S")
        )


def test_renamed_sensor_is_refused_with_expected_and_found(tmp_path, records):
    dev, test = records
    path = tmp_path / "renamed.h5"
    write_ncmapss(path, dev, test)
    _rename_columns(path, "X_s", {"T24": "T_24", "T30": "T 30"})
    for read in (lambda: load_ncmapss(path, "dev"), lambda: ncmapss_info(path)):
        with pytest.raises(ValueError) as err:
            read()
        msg = str(err.value)
        assert "renamed.h5" in msg
        assert "X_s_var: unknown ['T_24', 'T 30'], missing ['T24', 'T30']" in msg
        assert f"expected (any order) {list(MEASURED_SENSOR_NAMES)}" in msg
        assert "found ['T_24', 'T 30', 'T48'" in msg and "rename=" in msg
    # Before: T_24 and T 30 went silently to Record.extras and T24 / T30 vanished.
    with pytest.raises(ValueError, match="X_s_var: unknown"):
        load_ncmapss(path, "dev", sensors=["Nf"])


def test_rename_maps_the_file_names(tmp_path, records):
    dev, test = records
    path = tmp_path / "renamed.h5"
    write_ncmapss(path, dev, test)
    _rename_columns(path, "X_s", {"T24": "T_24"})
    _rename_columns(path, "T", {"HPT_eff_mod": "HPT_eff"})
    rename = {"T_24": "T24", "HPT_eff": "HPT_eff_mod"}
    assert_records_equal(load_ncmapss(path, "dev", rename=rename), dev)
    assert ncmapss_info(path, rename=rename)["columns"]["X_s"][0] == "T24"
    with pytest.raises(ValueError, match="rename names column\\(s\\) \\['T_99'\\]"):
        load_ncmapss(path, "dev", rename={**rename, "T_99": "T24"})
    with pytest.raises(ValueError, match="X_s_var: .*repeated \\['T30'\\]"):
        load_ncmapss(path, "dev", rename={**rename, "T30": "T30", "T48": "T30"})


@pytest.mark.parametrize(
    "group, mapping, match",
    [
        ("T", {"LPT_flow_mod": "LPT_flow"}, "T_var: unknown \\['LPT_flow'\\]"),
        ("W", {"alt": "altitude"}, "W_var: unknown \\['altitude'\\], missing"),
        ("A", {"hs": "health"}, "A_var: unknown \\['health'\\], missing \\['hs'\\]"),
        ("X_v", {"T40": "T30"}, "in both X_s_var and X_v_var"),
    ],
)
def test_unknown_names_in_any_group_are_refused(
    tmp_path, records, group, mapping, match
):
    dev, test = records
    path = tmp_path / "data.h5"
    write_ncmapss(path, dev, test)
    _rename_columns(path, group, mapping)
    with pytest.raises(ValueError, match=match):
        load_ncmapss(path, "dev")


def _poisoned(records):
    """The dev record with NaN in T24 (rows 3, 4, 9), Inf in alt (row 9) and NaN in
    theta (row 20); unit 2 is rows 7..17."""
    dev, test = records
    w, x, theta = dev.w.copy(), dev.x.copy(), dev.theta.copy()
    x[[3, 4, 9], NCMAPSS_SENSORS.index("T24")] = np.nan
    w[9, 0] = np.inf
    theta[20, 6] = np.nan
    return dataclasses.replace(dev, w=w, x=x, theta=theta), test


def test_nonfinite_rows_are_refused_naming_file_column_rows_count(tmp_path, records):
    dev, test = _poisoned(records)
    path = tmp_path / "nan.h5"
    write_ncmapss(path, dev, test)
    with pytest.raises(ValueError) as err:
        load_ncmapss(path, "dev")
    msg = str(err.value)
    assert "nan.h5 [dev]" in msg and "in 4 of 23 rows" in msg
    assert "column T24: 3 rows (rows 3, 4, 9)" in msg
    assert "column alt: 1 row (row 9)" in msg
    assert "column HPT_eff_mod: 1 row (row 20)" in msg
    assert "nonfinite='drop'" in msg and "dataset.nonfinite=drop" in msg
    # Rows are the file's rows, also through a unit selection and a stride.
    with pytest.raises(ValueError, match="column T24: 1 row \\(row 9\\)"):
        load_ncmapss(path, "dev", units=[2], stride=3, block_rows=2)
    assert len(load_ncmapss(path, "test")) == 15  # the clean split still loads
    # A sensor that is not loaded cannot poison the load.
    assert len(load_ncmapss(path, "dev", rows=(10, 20), sensors=["Nf"])) == 10


def test_nonfinite_drop_reports_rows_per_column(tmp_path, records):
    dev, test = _poisoned(records)
    path = tmp_path / "nan.h5"
    write_ncmapss(path, dev, test)
    got = load_ncmapss(path, "dev", nonfinite="drop")
    keep = np.ones(23, bool)
    keep[[3, 4, 9, 20]] = False
    assert_records_equal(got, dev.take(keep))
    assert got.dropped == {"alt": 1, "T24": 3, "HPT_eff_mod": 1}
    assert got.dropped_rows == 4
    assert got.take(slice(0, 3)).dropped_rows == 4  # the report travels with the rows
    kept = load_ncmapss(path, "dev", nonfinite="keep")
    assert np.isnan(kept.x).sum() == 3 and kept.dropped_rows == 0
    with pytest.raises(ValueError, match="nonfinite must be one of"):
        load_ncmapss(path, "dev", nonfinite="ignore")


def test_nonfinite_unit_id_is_refused_even_when_kept(tmp_path, records):
    dev, test = records
    path = tmp_path / "nan.h5"
    write_ncmapss(path, dev, test)
    with h5py.File(path, "a") as f:
        f["A_dev"][5, AUX_NAMES.index("unit")] = np.nan
    with pytest.raises(ValueError, match="column unit: 1 row \\(row 5\\)"):
        load_ncmapss(path, "dev", nonfinite="keep")
    got = load_ncmapss(path, "dev", nonfinite="drop")
    assert got.dropped == {"unit": 1} and len(got) == 22
    assert ncmapss_info(path)["splits"]["dev"]["units"] == [1, 2, 3]
