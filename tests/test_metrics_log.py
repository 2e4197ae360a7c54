"""Tests for the JSONL metrics writer and reader."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.runs.metrics_log import MetricsWriter, read_metrics


def metrics_columns(records):
    """Numeric scalar metrics as columns ``{name: values}`` (NaN where missing): how
    a reader of the log tabulates it."""
    names = sorted(
        {k for r in records for k, v in r.items() if isinstance(v, bool | int | float)}
    )
    return {
        name: np.array([r.get(name, np.nan) for r in records], dtype=float)
        for name in names
    }


def test_round_trip_converts_numpy_and_jax_values(tmp_path):
    path = tmp_path / "logs" / "metrics.jsonl"
    with MetricsWriter(path) as writer:
        writer.write(
            np.int64(10),
            {
                "loss": jnp.float32(0.5),
                "lr": np.float64(1e-4),
                "done": np.bool_(True),
                "per_sensor": jnp.arange(3.0),
                "bad": float("nan"),
            },
        )
        writer.write(20, {"loss": 0.25, "bad": math.inf})
        # Flushed per write: readable before the writer is closed.
        assert len(read_metrics(path)) == 2
    records = read_metrics(path)
    assert records[0] == {
        "step": 10,
        "loss": 0.5,
        "lr": 1e-4,
        "done": True,
        "per_sensor": [0.0, 1.0, 2.0],
        "bad": records[0]["bad"],
    }
    assert math.isnan(records[0]["bad"]) and records[1]["bad"] == math.inf
    columns = metrics_columns(records)
    np.testing.assert_array_equal(columns["step"], [10, 20])
    np.testing.assert_array_equal(columns["loss"], [0.5, 0.25])
    np.testing.assert_array_equal(columns["lr"], [1e-4, np.nan])
    assert "per_sensor" not in columns


def test_append_mode_keeps_earlier_records(tmp_path):
    path = tmp_path / "m.jsonl"
    with MetricsWriter(path) as writer:
        writer.write(1, {"a": 1})
    with MetricsWriter(path) as writer:
        writer.write(2, {"a": 2})
    assert [r["step"] for r in read_metrics(path)] == [1, 2]


def test_truncated_last_line_is_skipped_but_corruption_raises(tmp_path):
    path = tmp_path / "m.jsonl"
    path.write_text('{"step": 1, "a": 1}\n{"step": 2, "a"')
    with pytest.warns(UserWarning, match="truncated"):
        assert read_metrics(path) == [{"step": 1, "a": 1}]
    path.write_text('{"step": 1\n{"step": 2}\n')
    with pytest.raises(ValueError, match=":1: not a JSON record"):
        read_metrics(path)


def test_bad_values_are_rejected(tmp_path):
    with MetricsWriter(tmp_path / "m.jsonl") as writer:
        with pytest.raises(ValueError, match="reserved"):
            writer.write(0, {"step": 1})
        with pytest.raises(ValueError, match="cannot log"):
            writer.write(0, {"obj": object()})
