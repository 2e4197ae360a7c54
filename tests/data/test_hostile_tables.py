"""Tables as a careless user or a faulty pipeline gives them (issue 25): an index
holding the units, repeated column names, no rows, the wrong type, ``ignore=`` of a
used column, repeated times, a unit in two splits. Each is read correctly or is an
error naming the columns, units or times; never a silent single unit or a raw
numpy error."""

import numpy as np
import pandas as pd
import pytest

from jaxcal.data.readers import dataset_from_arrays, read_dataset


def _frame():
    """Two units of three rows, unit 2's rows listed first and out of time order."""
    return pd.DataFrame(
        {
            "unit": [2, 2, 2, 1, 1, 1],
            "time": [2.0, 0.0, 1.0, 0.0, 1.0, 2.0],
            "a": np.arange(6.0),
            "b": np.arange(6.0) + 10,
            "y1": np.arange(6.0) + 20,
            "y2": np.arange(6.0) + 30,
        }
    )


@pytest.mark.parametrize("levels", [["unit", "time"], ["unit"]])
def test_an_index_of_units_and_times_is_read_as_those_columns(model, levels):
    flat = read_dataset(_frame(), model)
    indexed = read_dataset(_frame().set_index(levels), model)
    assert indexed.units.tolist() == [2, 1]  # not one unit
    np.testing.assert_array_equal(indexed.unit, flat.unit)
    np.testing.assert_array_equal(indexed.time, flat.time)
    np.testing.assert_array_equal(indexed.x, flat.x)
    kept = read_dataset(_frame().set_index("unit", drop=False), model)
    np.testing.assert_array_equal(kept.unit, flat.unit)


def test_a_multiindex_of_other_levels_is_refused_or_renamed(model):
    frame = _frame().rename(columns={"unit": "engine"}).set_index(["engine", "time"])
    with pytest.raises(ValueError, match=r"index has levels \['engine', 'time'\]"):
        read_dataset(frame, model)
    data = read_dataset(frame, model, rename={"engine": "unit"})
    assert data.units.tolist() == [2, 1]


def test_two_columns_of_one_name_are_named(model):
    frame = _frame()
    frame.columns = ["unit", "time", "a", "b", "y1", "y1"]
    with pytest.raises(ValueError, match=r"2 columns are named 'y1'"):
        read_dataset(frame, model)
    with pytest.raises(
        ValueError, match=r"columns \['a', 'z'\] are all renamed to 'a'"
    ):
        read_dataset(_frame().assign(z=1.0), model, rename={"z": "a"})


def test_a_table_without_rows_is_named(model, tmp_path):
    with pytest.raises(ValueError, match=r"no rows in DataFrame"):
        read_dataset(_frame().iloc[:0], model)
    path = tmp_path / "header.csv"
    path.write_text("a,b,y1,y2\n")
    with pytest.raises(ValueError, match=rf"no rows in {path}"):
        read_dataset(path, model)
    with pytest.raises(ValueError, match=r"no rows in arrays"):
        dataset_from_arrays(np.zeros((0, 2)), np.zeros((0, 2)), model)


def test_rows_all_dropped_for_nonfinite_values_are_named(model):
    # (one output missing everywhere would leave partial rows, kept: every output is)
    frame = _frame().assign(y1=np.nan, y2=np.nan)
    with pytest.raises(ValueError, match=r"every row has a non-finite value"):
        read_dataset(frame, model, nonfinite="drop")


@pytest.mark.parametrize(
    "data", [np.zeros((3, 4)), [1.0, 2.0], None, {"a": [1.0]}], ids=type
)
def test_data_of_another_type_says_the_accepted_types(model, data):
    with pytest.raises(ValueError, match=r"expected a file path .* a pandas DataFrame"):
        read_dataset(data, model)


def test_ignore_of_a_condition_is_an_error_and_of_an_output_is_honoured(model):
    with pytest.raises(ValueError, match=r"ignore=\('a',\) names the condition"):
        read_dataset(_frame(), model, ignore=("a",))
    data = read_dataset(_frame(), model, ignore=("y1",))
    assert data.output_names == ("y2",)  # not read, as asked
    one = read_dataset(_frame(), model, ignore=("unit", "time"))
    assert one.units.tolist() == [0]


def test_a_time_repeated_within_a_unit_is_named(model):
    frame = _frame()
    frame.loc[1, "time"] = 2.0  # unit 2 now has time 2.0 twice
    with pytest.raises(ValueError, match=r"unit 2: time \[2.0\]"):
        read_dataset(frame, model)
    with pytest.raises(ValueError, match=r"unit 0: time \[1.0\]"):
        dataset_from_arrays(np.ones((2, 2)), np.ones((2, 2)), model, time=[1, 1])
    # the same time in two units is fine
    assert read_dataset(_frame(), model).num_rows == 6


def test_a_unit_in_two_splits_is_named(model):
    frame = _frame().assign(split=["train", "test", "train", "test", "test", "test"])
    with pytest.raises(ValueError, match=r"unit 2: \['test', 'train'\]"):
        read_dataset(frame, model)
    ok = _frame().assign(split=["train"] * 3 + ["test"] * 3)
    assert read_dataset(ok, model).select_split("test").units.tolist() == [1]
