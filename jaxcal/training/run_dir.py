"""The layout of a run folder and the host-side file operations on it.

``runs/<name>/`` holds::

    config.json        the resolved TrainConfig (read by jaxcal.checkpoint.load_config)
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
A folder that holds only ``config.json`` (a start that failed before this version
checked everything first) holds no run and does not block another config.

All files are written atomically (:func:`write_atomic`: temporary file, then
``os.replace``). A temporary file is named ``.<target>.<host>.<pid>.<random>.tmp``;
the next write to the same target removes those whose writer has died (killed
mid-way), never one of a live writer (:func:`remove_stale_temps`).
"""

from __future__ import annotations

import json
import os
import re
import socket
import tempfile
from pathlib import Path
from typing import Any

from jaxcal.checkpoint import CONFIG_FILE
from jaxcal.metrics_log import read_metrics, to_json_value
from jaxcal.settings import check_output_path, config_to_dict

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


# Temporary files this process is writing now: a same-pid temp file is stale only
# when it is not one of these (the pid of a dead writer may have been reused).
_LIVE_TEMPS: set[str] = set()


def _host_tag() -> str:
    """This machine's name as a file-name token (pids mean nothing across hosts)."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:40] or "host"


def is_pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this host (signal 0 only probes)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        return True
    except (OverflowError, ValueError):
        return False
    return True


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files of ``path`` left by writers that died.

    A temp file of ``path`` is ``.<name>.<host>.<pid>.<random>.tmp`` beside it. It is
    removed only when it was made on this host by a pid that no longer runs, or by
    this process but is not being written now; a live writer's file (this or another
    process, another host) and files of any other name are left alone.

    Args:
        path: the target file.

    Returns:
        The removed files.
    """
    path = Path(path)
    pattern = re.compile(
        re.escape(f".{path.name}.") + r"([A-Za-z0-9-]+)\.(\d+)\.[a-z0-9_]+\.tmp"
    )
    try:
        names = os.listdir(path.parent)
    except OSError:
        return []
    host, pid = _host_tag(), os.getpid()
    removed = []
    for name in names:
        match = pattern.fullmatch(name)
        if match is None or match[1] != host:
            continue
        tmp = path.parent / name
        owner = int(match[2])
        stale = str(tmp) not in _LIVE_TEMPS if owner == pid else not is_pid_alive(owner)
        if stale:
            try:
                tmp.unlink()
            except FileNotFoundError:  # removed meanwhile by another writer
                continue
            removed.append(tmp)
    return removed


def make_temp(path: str | os.PathLike) -> tuple[int, str]:
    """Create the temporary file of a write to ``path``, after removing stale ones.

    Args:
        path: the target file; its folder must exist.

    Returns:
        ``(fd, tmp)``: an open descriptor and the name of a new empty file
        ``.<name>.<host>.<pid>.<random>.tmp`` beside ``path`` (mode 0600). Call
        :func:`release_temp` once it is renamed or given up.
    """
    path = Path(path)
    remove_stale_temps(path)
    prefix = f".{path.name}.{_host_tag()}.{os.getpid()}."
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=prefix, suffix=".tmp")
    _LIVE_TEMPS.add(tmp)
    return fd, tmp


def release_temp(tmp: str | os.PathLike) -> None:
    """End the life of a temp file of :func:`make_temp`: delete it if still there."""
    _LIVE_TEMPS.discard(os.fspath(tmp))
    Path(tmp).unlink(missing_ok=True)


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` to a temporary file beside ``path``, then rename it over ``path``
    (a reader never sees half a file); creates the folder; removes temp files of
    ``path`` left by killed writers (:func:`remove_stale_temps`); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = make_temp(path)
    try:
        with os.fdopen(fd, "wb" if isinstance(data, bytes) else "w") as f:
            f.write(data)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600 files; results are for sharing
        os.replace(tmp, path)
    finally:
        release_temp(tmp)
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
    """
    run_dir = Path(run_dir)
    check_output_path(os.fspath(run_dir), "output.runs_dir/name", folder=True)
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
    write_json(Path(run_dir) / CONFIG_FILE, config_to_dict(cfg))
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
