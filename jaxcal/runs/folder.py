"""The layout of a run folder and the host-side file operations on it.

``runs/<name>/`` holds::

    config.json        the resolved TrainConfig (jaxcal.runs.checkpoint.load_config)
    data.json          sensors, declared parameters, units, action box, normalisation
    surrogate/         Orbax checkpoint of the surrogate D (step 0)
    surrogate.json     D's fit history and per-sensor one-step / free-running errors
    checkpoints/       Orbax checkpoints of the runner state, step = chunks done
    policy/            the deployable PolicyParams at the same steps (jaxcal.deploy)
    policy_best/       the policy of the chunk with the lowest validation tracking RMSE
    metrics.jsonl      one record per chunk (jaxcal.runs.metrics_log)
    final.json         test scores, wall time, throughput and time to target of the
                       finished run, and the 90 % band's test coverage
    uncertainty.json   the kept policy's split-conformal theta band, fitted on the
                       validation units (jaxcal.calibrators.uncertainty.conformal)
    model/             the copy of a model file the run was trained on, which
                       loading the run uses (jaxcal.training.model_source)
    .lock              held by the one training of the run (jaxcal.runs.lock)

The name is one folder inside ``runs_dir`` (``name=../x`` or an absolute name is
refused, :func:`jaxcal.runs.lock.check_run_name`).

Rerunning with the same name resumes: the stored config must match the new one except
for the fields that do not change the training trajectory (:data:`RESUMABLE_FIELDS`).
A folder that holds only ``config.json`` (a start that failed before this version
checked everything first) holds no run and does not block another config.

All files are written atomically (:func:`jaxcal.runs.atomic.write_atomic`: temporary
file, then ``os.replace``; temp files of killed writers are removed by the next
write to the same target).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from jaxcal.runs.atomic import (  # noqa: F401 (re-exported: one import path)
    make_temp,
    write_atomic,
)
from jaxcal.runs.checkpoint import CONFIG_FILE, save_config
from jaxcal.runs.lock import check_not_in_use
from jaxcal.runs.metrics_log import read_metrics, to_json_value
from jaxcal.settings import check_output_path, config_to_dict

DATA_FILE = "data.json"
SURROGATE_DIR = "surrogate"
SURROGATE_FILE = "surrogate.json"
CHECKPOINT_DIR = "checkpoints"
POLICY_DIR = "policy"
POLICY_BEST_DIR = "policy_best"
# the kept policy tuned by gradient through the filter (tune.steps; loaded first)
POLICY_TUNED_DIR = "policy_tuned"
METRICS_FILE = "metrics.jsonl"
FINAL_FILE = "final.json"
EVALUATION_FILE = "evaluate.json"
# Top-level fields (and budget / output sub-fields) a resumed run may change.
RESUMABLE_FIELDS: dict[str, tuple[str, ...] | None] = {
    "budget": None,  # None: every sub-field
    "tune": None,
    "output": ("progress", "max_to_keep"),
}


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


def _holds_run(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds anything of a run beyond ``config.json`` and temps."""
    return any(
        entry.name != CONFIG_FILE and not entry.name.startswith(".")
        for entry in run_dir.iterdir()
    )


def check_run_dir(run_dir: str | os.PathLike, cfg: Any) -> str:
    """How a run of ``cfg`` would use ``run_dir``, without writing anything.

    Args:
        run_dir: ``runs/<name>``.
        cfg: the resolved config (a frozen dataclass).

    Returns:
        ``"new"`` (no folder, or an empty one), ``"resume"`` (a run of the same
        config) or ``"stale"`` (only the ``config.json`` of a start that failed before
        training: it is overwritten).

    Raises:
        ValueError: ``run_dir`` cannot be created or written, or it holds a run whose
            stored config differs from ``cfg`` in a field that changes training (the
            message lists the differences).
        RunInUseError: another process trains the run now (a ``ValueError``).
    """
    run_dir = Path(run_dir)
    check_output_path(os.fspath(run_dir), "output.runs_dir/name", folder=True)
    check_not_in_use(run_dir)  # a hint only: hold_run is the lock
    stored_path = run_dir / CONFIG_FILE
    if not stored_path.is_file():
        return "new"
    if not _holds_run(run_dir):
        return "stale"
    try:
        old = json.loads(stored_path.read_text())
    except ValueError as err:
        raise ValueError(
            f"{stored_path} is not valid JSON ({err}); choose another name= "
            "(output.name=) or delete the folder"
        ) from None
    diffs = _differences(_comparable(old), _comparable(config_to_dict(cfg)))
    if diffs:
        raise ValueError(
            f"{run_dir} holds a run with a different config ("
            + "; ".join(diffs)
            + "); choose another name= (output.name=) or delete the folder"
        )
    return "resume"


def prepare_run_dir(run_dir: str | os.PathLike, cfg: Any) -> bool:
    """Create the run folder (or check an existing one, :func:`check_run_dir`) and
    write the resolved ``config.json``.

    Call it only once every check of the config and the data has passed, so that a
    failed start leaves no folder behind.

    Args:
        run_dir: ``runs/<name>``.
        cfg: the resolved config (a frozen dataclass).

    Returns:
        True when the folder already held a run (a resume), False for a new run.

    Raises:
        ValueError: see :func:`check_run_dir`.
    """
    resumed = check_run_dir(run_dir, cfg) == "resume"
    save_config(run_dir, cfg)  # the one writer of config.json
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
        write_atomic(path, "".join(json.dumps(r) + "\n" for r in kept))
    return kept
