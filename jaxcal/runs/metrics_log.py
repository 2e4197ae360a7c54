"""Host-side JSON-lines metrics log: one ``{"step": ..., name: value, ...}`` per line.

Training loops hand the metrics dict returned by a jitted chunk to
:meth:`MetricsWriter.write` after ``jax.device_get``; values may be Python numbers,
NumPy or JAX scalars, or small arrays (stored as nested lists). The file is opened in
append mode and flushed after every line, so a crashed or resumed run keeps everything
written so far and a live run can be followed with ``tail -f``. Non-finite floats are
written as ``NaN`` / ``Infinity`` (Python's JSON dialect), which :func:`read_metrics`
reads back. Host-only leaf: never imported by traced code.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np


def to_json_value(value: Any) -> Any:
    """Plain-Python form of a metric value (scalars to int/float/bool, arrays to lists).

    Raises:
        ValueError: for values that are neither numbers, strings, arrays nor
            lists/dicts of those.
    """
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, Mapping):
        return {str(k): to_json_value(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_json_value(v) for v in value]
    if hasattr(value, "__array__") or isinstance(value, np.generic):
        array = np.asarray(value)
        if array.dtype.kind not in "biuf":
            raise ValueError(f"metric arrays must be numeric, got dtype {array.dtype}")
        return array.tolist()  # 0-d arrays give a Python scalar
    raise ValueError(f"cannot log metric value {value!r} of type {type(value)}")


class MetricsWriter:
    """Append metrics records to a JSONL file.

    Args:
        path: the ``.jsonl`` file; its folder is created if missing.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "a", encoding="utf-8")

    def write(self, step: int, metrics: Mapping[str, Any]) -> None:
        """Append one record ``{"step": step, **metrics}`` and flush it.

        Raises:
            ValueError: a metric is named ``step`` or has an unloggable value.
        """
        if "step" in metrics:
            raise ValueError("metric name 'step' is reserved for the record's step")
        record = {"step": int(step)}
        record.update({str(k): to_json_value(v) for k, v in metrics.items()})
        self._file.write(json.dumps(record) + "\n")
        self._file.flush()

    def close(self) -> None:
        """Close the file (idempotent)."""
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> MetricsWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def read_metrics(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Records of a JSONL metrics file, in file order.

    A final line cut short by a crash mid-write is skipped with a warning; a malformed
    line anywhere else raises ``ValueError`` naming the line number.
    """
    lines = Path(path).read_text(encoding="utf-8").split("\n")
    records = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as err:
            is_last = number == len(lines)  # no trailing newline: write was cut short
            if is_last:
                warnings.warn(f"{path}: skipped truncated last line", stacklevel=2)
                continue
            raise ValueError(f"{path}:{number}: not a JSON record ({err})") from None
    return records
