"""The layout of a run folder and the host-side file operations on it.

``runs/<name>/`` holds::

    config.json        the resolved TrainConfig (jaxcal.checkpoint.save_config)
    data.json          sensors, declared parameters, units, action box, normalisation
    surrogate/         Orbax checkpoint of the surrogate D (step 0)
    surrogate.json     D's fit history and per-sensor one-step / free-running errors
    checkpoints/       Orbax checkpoints of the runner state, step = chunks done
    policy/            the deployable PolicyParams at the same steps (jaxcal.deploy)
    policy_best/       the policy of the chunk with the lowest validation tracking RMSE
    metrics.jsonl      one record per chunk (jaxcal.metrics_log)
    final.json         test scores, wall time and throughput of the finished run

Rerunning with the same name resumes: the stored config must match the new one except
for the fields that do not change the training trajectory (:data:`RESUMABLE_FIELDS`).
All JSON files are written atomically (temporary file, then ``os.replace``).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from jaxcal.checkpoint import CONFIG_FILE, save_config
from jaxcal.cli_args import config_to_dict
from jaxcal.metrics_log import read_metrics, to_json_value

DATA_FILE = "data.json"
SURROGATE_DIR = "surrogate"
SURROGATE_FILE = "surrogate.json"
CHECKPOINT_DIR = "checkpoints"
POLICY_DIR = "policy"
POLICY_BEST_DIR = "policy_best"
METRICS_FILE = "metrics.jsonl"
FINAL_FILE = "final.json"
EVALUATION_FILE = "evaluate.json"
# Top-level fields (and budget / output sub-fields) a resumed run may change.
RESUMABLE_FIELDS: dict[str, tuple[str, ...] | None] = {
    "budget": None,  # None: every sub-field
    "output": ("progress", "max_to_keep"),
}


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` to a temporary file beside ``path``, then rename it over ``path``
    (a reader never sees half a file); creates the folder; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb" if isinstance(data, bytes) else "w") as f:
            f.write(data)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600 files; results are for sharing
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` (made JSON-ready) to ``path`` atomically; returns the path."""
    return write_atomic(path, json.dumps(to_json_value(data), indent=2) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    """Parsed JSON of ``path``, or a ``FileNotFoundError`` naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"missing {path}")
    return json.loads(path.read_text())


def _comparable(data: dict) -> dict:
    out = dict(data)
    for field, subfields in RESUMABLE_FIELDS.items():
        if field not in out:
            continue
        if subfields is None:
            out.pop(field)
        else:
            out[field] = {k: v for k, v in out[field].items() if k not in subfields}
    return out


def _differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        keys = sorted(set(old) | set(new))
        return [
            d
            for k in keys
            for d in _differences(old.get(k), new.get(k), f"{prefix}{k}.")
        ]
    return [] if old == new else [f"{prefix[:-1]}: {old!r} -> {new!r}"]


def prepare_run_dir(run_dir: str | os.PathLike, cfg: Any) -> bool:
    """Create the run folder, or check that an existing one was made by ``cfg``.

    Args:
        run_dir: ``runs/<name>``.
        cfg: the resolved config (a frozen dataclass).

    Returns:
        True when the folder already held a run (a resume), False for a new run.

    Raises:
        ValueError: the stored config differs from ``cfg`` in a field that changes
            training; the message lists the differences.
    """
    run_dir = Path(run_dir)
    new = config_to_dict(cfg)
    stored_path = run_dir / CONFIG_FILE
    resumed = stored_path.is_file()
    if resumed:
        old = json.loads(stored_path.read_text())
        diffs = _differences(_comparable(old), _comparable(new))
        if diffs:
            raise ValueError(
                f"{run_dir} holds a run with a different config ("
                + "; ".join(diffs)
                + "); choose another name= (output.name=) or delete the folder"
            )
    save_config(run_dir, new)
    return resumed


def truncate_metrics(path: str | os.PathLike, last_step: int) -> list[dict]:
    """Drop records with ``step > last_step`` (chunks run after the last checkpoint).

    Returns:
        The kept records. The file is rewritten atomically (or removed when empty).
    """
    path = Path(path)
    if not path.is_file():
        return []
    records = read_metrics(path)
    kept = [r for r in records if int(r["step"]) <= last_step]
    if len(kept) != len(records):
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
        with os.fdopen(fd, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in kept)
        os.replace(tmp, path)
    return kept
