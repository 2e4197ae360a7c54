"""The one atomic writer: a reader never sees half a file, a killed writer leaves
nothing that lasts.

:func:`write_atomic` writes to a temporary file beside the target, then renames it
over the target (``os.replace``). A temporary file is named
``.<target>.<host>.<pid>.<random>.tmp``; the next write to the same target removes
those whose writer has died (killed mid-way), never one of a live writer
(:func:`remove_stale_temps`). Writers that stream into a file of their own (the
N-CMAPSS writer, the fleet results file, figures) take their temp file from
:func:`make_temp` and end it with :func:`release_temp`. A host-only leaf: it imports
nothing of jaxcal.
"""

from __future__ import annotations

import os
import re
import socket
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

# Temporary files this process is writing now: a same-pid temp file is stale only
# when it is not one of these (the pid of a dead writer may have been reused).
_LIVE_TEMPS: set[str] = set()


def host_tag() -> str:
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
    host, pid = host_tag(), os.getpid()
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
    prefix = f".{path.name}.{host_tag()}.{os.getpid()}."
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
    return write_atomic_with(
        path, lambda f: f.write(data), binary=isinstance(data, bytes)
    )


def write_atomic_with(
    path: str | os.PathLike, write: Callable[[IO], Any], *, binary: bool = True
) -> Path:
    """:func:`write_atomic` of what ``write(file)`` writes into the open temporary
    file (a figure's ``savefig``, a Parquet table's writer); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = make_temp(path)
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600 files; results are for sharing
        os.replace(tmp, path)
    finally:
        release_temp(tmp)
    return path
