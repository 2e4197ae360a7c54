"""Who may write a run folder, and where: names confined to the runs folder, and one
training of a run at a time.

A run name is one folder name inside ``output.runs_dir``
(:func:`check_run_name`): ``name=../x``, an absolute name or one with a path
separator would write elsewhere, and is refused before anything is read.

A training holds its run folder's lock (:func:`hold_run`) from its first write to
its last: ``fcntl.flock`` on ``<run>/.lock``, an OS lock that the kernel releases
when its process ends, however it ends, so a killed training never blocks the next
one, while a live one makes a second training of the name fail at once with who
holds it (pid, host, start, command; the lock file's content, rewritten by each
holder). Why not the ``filelock`` package: it would be a new dependency for the
same ``flock`` call, and it neither tells who holds a lock nor fails at once without
a timeout loop. The lock file stays (empty) after a run: it is a dot-file, which
nothing reading a run looks at, and deleting it would open a race between a
process that just opened it and one that creates a new one. ``flock`` is advisory
and local: it guards trainings through this module on one machine (over NFS it
holds only where the server supports locks).

Host-only and imports nothing of jaxcal beyond :mod:`jaxcal.runs.atomic`, so the config
checks a name before any heavy import.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from jaxcal.runs.atomic import host_tag

LOCK_FILE = ".lock"
NAME_FORM = (
    "one folder name inside output.runs_dir, e.g. my-run_2 (no '/' or '\\', no "
    "'..', not starting with '.')"
)
# A probe (check_not_in_use) holds the lock for microseconds: an acquirer that meets
# it retries for this long before it calls the run busy.
_RETRY_S = 0.5
# Run folders this process holds (resolved paths), which its own probes skip.
_HELD: set[str] = set()


class RunInUseError(ValueError):
    """Another training holds the run folder (a ``ValueError``: exit code 2)."""


def check_run_name(name: str, field: str = "name") -> str:
    """``name``, or a ``ValueError`` naming ``field`` when it is not one folder name.

    Refused: empty, absolute, a path separator (``/`` or ``\\`` on every system, so
    that a run folder means the same everywhere), ``..`` anywhere, a leading ``.``
    (hidden, and ``.``/``..`` themselves) and control characters.
    """
    why = None
    if not name or not name.strip():
        why = "it is empty"
    elif os.path.isabs(name) or name.startswith(("/", "\\")):
        why = "it is an absolute path"
    elif ".." in name:
        why = "it holds '..'"
    elif "/" in name or "\\" in name or (os.altsep and os.altsep in name):
        why = "it holds a path separator"
    elif name.startswith("."):
        why = "it starts with '.'"
    elif any(ord(c) < 32 or ord(c) == 127 for c in name):
        why = "it holds a control character"
    if why is not None:
        raise ValueError(f"{field}={name!r}: {why}; a run name must be {NAME_FORM}")
    return name


def run_folder(runs_dir: str | os.PathLike, name: str) -> Path:
    """``runs_dir / name`` after :func:`check_run_name`."""
    return Path(runs_dir) / check_run_name(name)


def _holder(path: Path) -> str:
    """Who holds the lock, as its holder wrote it (best effort: it may be writing)."""
    try:
        info = json.loads(path.read_text() or "{}")
    except (OSError, ValueError):
        info = {}
    if not info:
        return "another process (it has not written its details yet)"
    return (
        f"pid {info.get('pid')} on host {info.get('host')}, since "
        f"{info.get('started')} ({info.get('command')})"
    )


def _busy(run_dir: Path, lock: Path) -> RunInUseError:
    return RunInUseError(
        f"run {run_dir} is in use: a training of it holds {lock} — "
        f"{_holder(lock)}; wait for it to end or choose another name= "
        "(output.name=). A lock dies with its process: a killed training does not "
        "keep it."
    )


def _try_lock(fd: int) -> bool:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        raise
    return True


def check_not_in_use(run_dir: str | os.PathLike) -> None:
    """Fail early, writing nothing, when another process holds ``run_dir``'s lock.

    Only a hint (the holder may start or end right after): :func:`hold_run` is the
    lock. A folder this process holds passes.

    Raises:
        RunInUseError: naming the folder and its holder.
    """
    run_dir = Path(run_dir)
    lock = run_dir / LOCK_FILE
    if str(run_dir.resolve()) in _HELD:
        return
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:  # no lock file (a new run) or unreadable: hold_run decides
        return
    try:
        if not _try_lock(fd):
            raise _busy(run_dir, lock)
    finally:
        os.close(fd)  # also releases the probe's lock


def _acquire(run_dir: Path, lock: Path) -> int:
    """An open descriptor of ``lock`` holding its flock (see :func:`hold_run`)."""
    deadline = time.monotonic() + _RETRY_S
    while True:
        run_dir.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except FileNotFoundError:  # a failed start removed the folder meanwhile
            fd = None
        if fd is not None and _try_lock(fd):
            try:  # the file we locked is still the one at the path
                if os.stat(lock).st_ino == os.fstat(fd).st_ino:
                    return fd
            except FileNotFoundError:
                pass
        if fd is not None:
            os.close(fd)
        if time.monotonic() > deadline:
            raise _busy(run_dir, lock)
        time.sleep(0.02)


@contextlib.contextmanager
def hold_run(run_dir: str | os.PathLike) -> Iterator[Path]:
    """Hold ``run_dir``'s lock (created with the folder if missing) for the block.

    The lock file gets this process's pid, host, start time and command, which a
    second training prints; on exit it is emptied and released. A folder this call
    created that holds nothing but the lock when the block fails is removed again,
    so a failed start leaves nothing behind.

    Raises:
        RunInUseError: another process (or another block of this one) holds it.
    """
    run_dir = Path(run_dir)
    lock = run_dir / LOCK_FILE
    created = not run_dir.exists()
    fd = _acquire(run_dir, lock)
    key = str(run_dir.resolve())
    _HELD.add(key)
    info = {
        "pid": os.getpid(),
        "host": host_tag(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "command": " ".join([os.path.basename(sys.executable), *sys.argv])[:300],
    }
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)
    failed = False
    try:
        yield run_dir
    except BaseException:
        failed = True
        raise
    finally:
        _HELD.discard(key)
        os.ftruncate(fd, 0)
        if failed and created and [p.name for p in run_dir.iterdir()] == [LOCK_FILE]:
            # still locked: a process that opened the file meanwhile finds it gone
            # from the path once it gets the lock, and starts over (_acquire)
            lock.unlink()
            with contextlib.suppress(OSError):
                run_dir.rmdir()
        os.close(fd)
