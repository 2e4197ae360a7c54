"""NASA C-MAPSS text reader, on fixtures written in the exact NASA format."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import jaxcal
from jaxcal.models.turbofan.data.cmapss_text import (
    EXTRA_MAP,
    SENSOR_MAP,
    load_cmapss_text,
)

# The six FD002 operating conditions (alt kft, Mach, TRA, T2 degR), data_facts.md §1.3.
CONDITIONS = (
    (0.0, 0.0, 100.0, 518.67),
    (10.0, 0.25, 100.0, 489.05),
    (20.0, 0.70, 100.0, 491.19),
    (25.0, 0.62, 60.0, 462.54),
    (35.0, 0.84, 100.0, 449.44),
    (42.0, 0.84, 100.0, 445.00),
)
# Per-sensor print formats of the NASA files (s1..s21), e.g. "... 0.02 334 2223 ...".
FORMATS = ["%.2f"] * 14 + ["%.4f", "%.2f", "%d", "%d", "%.2f", "%.2f", "%.4f"]


def sensor_values(unit, cycle, condition):
    """s1..s21 of a fabricated row: distinct per sensor, condition and cycle."""
    t2 = CONDITIONS[condition][3]
    values = [t2] + [
        100.0 * s + 10.0 * condition + 0.25 * cycle + unit for s in range(2, 22)
    ]
    values[16] = 390 + condition  # s17 htBleed is an integer column
    values[17] = 2388 + condition  # s18 Nf_dmd too
    return values


def nasa_line(unit, cycle, condition):
    alt, mach, tra, _ = CONDITIONS[condition]
    fields = [f"{unit:d}", f"{cycle:d}", f"{alt:.4f}", f"{mach:.4f}", f"{tra:.1f}"]
    values = sensor_values(unit, cycle, condition)
    fields += [f % v for f, v in zip(FORMATS, values, strict=True)]
    return " ".join(fields) + "  \n"  # NASA lines end in two spaces


def write_cmapss(path, lengths, num_conditions=1):
    """A C-MAPSS file: unit u (1-based) has lengths[u - 1] cycles."""
    lines = [
        nasa_line(u, c, (u + c) % num_conditions)
        for u, n in enumerate(lengths, start=1)
        for c in range(1, n + 1)
    ]
    Path(path).write_text("".join(lines))
    return path


def test_train_file_mapping_extras_and_rul(tmp_path):
    path = write_cmapss(tmp_path / "train_FD002.txt", [4, 6], num_conditions=6)
    rec = load_cmapss_text(path)
    assert len(rec) == 10 and rec.units.tolist() == [1, 2]
    assert rec.theta is None and np.isnan(rec.sample_rate_hz)
    assert np.isnan(rec.flight_class).all() and np.isnan(rec.hs).all()
    np.testing.assert_array_equal(rec.rul, [3, 2, 1, 0, 5, 4, 3, 2, 1, 0])
    # Row 6 is unit 2, cycle 2, condition (2 + 2) % 6 = 4.
    row, (alt, mach, tra, t2) = 5, CONDITIONS[4]
    np.testing.assert_allclose(rec.w[row], [alt * 1000, mach, tra, t2])
    s = sensor_values(2, 2, 4)
    for number, name in SENSOR_MAP.items():
        np.testing.assert_allclose(
            rec.columns([name])[row, 0], s[number - 1], atol=6e-3
        )
    for number, name in EXTRA_MAP.items():
        np.testing.assert_allclose(rec.extras[name][row], s[number - 1], atol=6e-3)
    assert rec.extras["op1_kft"][row] == alt and rec.extras["op3"][row] == tra
    assert rec.columns(["T24"])[row, 0] == pytest.approx(200 + 40 + 0.5 + 2)
    assert "Ps30" not in rec.x_names and "phi" not in rec.x_names


def test_test_file_rul_from_rul_file(tmp_path):
    path = write_cmapss(tmp_path / "test_FD001.txt", [3, 2])
    (tmp_path / "RUL_FD001.txt").write_text("112 \n98 \n")
    rec = load_cmapss_text(path, tmp_path / "RUL_FD001.txt")
    np.testing.assert_array_equal(rec.rul, [114, 113, 112, 99, 98])
    # Without the RUL file a truncated test series has unknown RUL, not a wrong one.
    np.testing.assert_array_equal(load_cmapss_text(path).rul, -1)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (
            lambda ls: ls.__setitem__(2, ls[2].replace("  \n", " 7  \n")),
            ":3: expected 26",
        ),
        (lambda ls: ls.__setitem__(1, ls[1].replace("1 2 ", "1 2.5 ", 1)), ":2: cycle"),
        (
            lambda ls: ls.__setitem__(3, ls[3].replace("0.0000", "abc", 1)),
            ":4: non-numeric",
        ),
        (lambda ls: ls.__delitem__(1), ":2: cycle 3 of unit 1 does not follow"),
        (lambda ls: ls.append(ls[0]), ":6: unit 1 reappears"),
    ],
)
def test_bad_lines_are_reported_by_line_number(tmp_path, mutate, match):
    path = write_cmapss(tmp_path / "train_FD001.txt", [3, 2])
    lines = path.read_text().splitlines(keepends=True)
    mutate(lines)
    path.write_text("".join(lines))
    with pytest.raises(ValueError, match=match):
        load_cmapss_text(path)


def test_missing_and_mismatched_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="train_FD009.txt"):
        load_cmapss_text(tmp_path / "train_FD009.txt")
    path = write_cmapss(tmp_path / "test_FD001.txt", [3, 2])
    (tmp_path / "RUL_FD001.txt").write_text("5\n")
    with pytest.raises(ValueError, match="1 RUL values but the test file has 2 units"):
        load_cmapss_text(path, tmp_path / "RUL_FD001.txt")
    with pytest.raises(ValueError, match="only meaningful for a test file"):
        load_cmapss_text(path, tmp_path / "RUL_FD001.txt", kind="train")


def test_the_turbofan_model_reads_its_files_through_read_dataset(tmp_path):
    path = write_cmapss(tmp_path / "train_FD001.txt", [3, 2])
    model = jaxcal.models.load("cmapss")
    assert sorted(model.file_readers) == [".h5", ".hdf5", ".txt"]
    data = jaxcal.read_dataset(path, model)
    assert data.num_rows == 5 and data.units.tolist() == [1, 2]
    with pytest.raises(ValueError, match="unknown data file type '.txt'"):
        jaxcal.read_dataset(path)  # the file's format is the model's


def _experiment_module():
    script = Path(__file__).resolve().parents[4] / "experiments" / "load_cmapss.py"
    spec = importlib.util.spec_from_file_location("load_cmapss_experiment", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_experiment_summarises_fd001_fd002(tmp_path):
    experiment = _experiment_module()
    for fd, conditions in (("FD001", 1), ("FD002", 6)):
        write_cmapss(tmp_path / f"train_{fd}.txt", [12, 12], num_conditions=conditions)
        write_cmapss(tmp_path / f"test_{fd}.txt", [5, 4, 3], num_conditions=conditions)
        (tmp_path / f"RUL_{fd}.txt").write_text("10\n20\n30\n")
    summary = experiment.summarise(tmp_path)
    assert summary["files"]["test_FD002.txt"] == {
        "rows": 12, "units": 3, "rul_min": 10, "rul_max": 32
    }  # fmt: skip
    conditions = summary["FD002_conditions"]
    assert [(c["alt_kft"], c["tra"], c["rows"]) for c in conditions] == [
        (alt, tra, 4) for alt, _, tra, _ in CONDITIONS
    ]
    # Condition k of unit u holds the cycles c with (u + c) % 6 == k.
    for k, cond in enumerate(conditions):
        cycles = [(u, c) for u in (1, 2) for c in range(1, 13) if (u + c) % 6 == k]
        expected_t30 = np.mean([sensor_values(u, c, k)[2] for u, c in cycles])
        assert cond["means"]["T30"] == pytest.approx(expected_t30, abs=1e-3)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        experiment.summarise(tmp_path / "nowhere")


def _with_tokens(path, edits):
    """Replace field ``col`` (0-based) of line ``number`` (1-based) by ``token``."""
    lines = path.read_text().splitlines(keepends=True)
    for number, col, token in edits:
        fields = lines[number - 1].split()
        fields[col] = token
        lines[number - 1] = " ".join(fields) + "  \n"
    path.write_text("".join(lines))
    return path


def test_non_numeric_token_names_file_line_and_column(tmp_path):
    path = write_cmapss(tmp_path / "train_FD001.txt", [3, 2])
    _with_tokens(path, [(4, 7, "12,5")])
    with pytest.raises(ValueError, match="train_FD001.txt:4: non-numeric value "
                       "'12,5' in column 8 \\(s3 \\(T30\\)\\)"):  # fmt: skip
        load_cmapss_text(path)
    _with_tokens(path, [(4, 7, "1.0"), (2, 1, "nan")])
    with pytest.raises(ValueError, match=":2: cycle must be an integer >= 1, got nan"):
        load_cmapss_text(path, nonfinite="drop")


def test_nonfinite_values_refused_or_dropped_with_a_report(tmp_path):
    path = write_cmapss(tmp_path / "train_FD001.txt", [3, 2])
    clean = load_cmapss_text(path)
    # T30 (s3, column 8) NaN on lines 2 and 3 (the last line of unit 1), htBleed Inf.
    _with_tokens(path, [(2, 7, "nan"), (3, 7, "NaN"), (5, 21, "inf")])
    with pytest.raises(ValueError) as err:
        load_cmapss_text(path)
    msg = str(err.value)
    assert "train_FD001.txt: non-finite values (NaN or Inf) in 3 of 5 lines" in msg
    assert "column s3 (T30): 2 lines (lines 2, 3)" in msg
    assert "column s17 (htBleed): 1 line (line 5)" in msg
    got = load_cmapss_text(path, nonfinite="drop")
    assert got.dropped == {"s3 (T30)": 2, "s17 (htBleed)": 1}
    assert got.dropped_rows == 3
    keep = np.array([True, False, False, True, False])
    np.testing.assert_array_equal(got.x, clean.x[keep])
    np.testing.assert_array_equal(got.rul, clean.rul[keep])  # RUL of the full file
    np.testing.assert_array_equal(got.cycle, [1, 1])
    kept = load_cmapss_text(path, nonfinite="keep")
    assert np.isnan(kept.columns(["T30"])).sum() == 2 and len(kept) == 5
