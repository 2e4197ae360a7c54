"""JAX's persistent compilation cache, on by default for jaxcal.

The programs jaxcal compiles — a filter over a fleet, the turbofan's Newton solve
(35-100 s each on a small CPU) — are the same from one process to the next: the
data, noise and prior are arguments, not constants (:mod:`jaxcal.calibrators.
compiled`). JAX can keep compiled programs on disk, keyed by the program, the JAX
version and the machine; with it on, a program compiles once per machine instead of
once per process.

On by default: the first :func:`jaxcal.calibrate` (and every jaxcal command line)
turns it on in ``$JAXCAL_CACHE_DIR`` or ``~/.cache/jaxcal/xla``, unless

* ``JAXCAL_CACHE=0`` (or ``off``/``false``) is set in the environment, or
  :func:`disable` was called: nothing is written or read; or
* the program already chose a cache directory (``jax_compilation_cache_dir``): that
  one is kept.

Importing jaxcal changes nothing (the switch happens at the first call, or at the
first :func:`jaxcal.models.load` of a built-in model). The traced programs of
jaxcal's own models, and of a user's model keyed by what it computes, are kept beside
the compiled ones, under the same switch (:mod:`jaxcal.calibrators.programs.on_disk`).

Trusting a cache: a cached entry is compiled machine code that the process loads and
runs, so anyone who can write to the directory can make jaxcal run their code (a
rewritten program returns wrong numbers without a word). The directory must be the
user's own: it is created with mode 0700, and an existing one that is owned by
another user, writable by its group or by others, or inside a folder others can
rename entries of (group/world-writable without the sticky bit) is not used: the
process runs without the on-disk cache, with one warning naming the folder and why
(:func:`private_problem`; ``docs/trust.md``). Deleting the cache is always safe: the
next call compiles again.
"""

from __future__ import annotations

import ctypes
import functools
import os
import stat
import warnings
from collections.abc import Callable

import jax

MIN_COMPILE_SECS = 0.2  # programs that compile faster are not worth a disk entry
_OFF = ("0", "off", "false", "no")
_state = {"disabled": False, "done": False}


def directory() -> str:
    """The default directory: ``$JAXCAL_CACHE_DIR`` or ``~/.cache/jaxcal/xla``."""
    return os.environ.get("JAXCAL_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "jaxcal", "xla"
    )


def enable_compilation_cache(path: str | None = None) -> None:
    """Persist compiled XLA programs in ``path`` (default :func:`directory`), unless
    switched off (``JAXCAL_CACHE=0`` or :func:`disable`)."""
    if _state["disabled"] or os.environ.get("JAXCAL_CACHE", "").lower() in _OFF:
        return
    path = path or directory()
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
        problem = private_problem(path)
    except OSError as err:
        problem = f"it cannot be created or read ({err})"
    if problem is not None:
        _state["done"] = True  # one warning per process, not one per call
        warn_bypassed(path, problem, stacklevel=3)
        return
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECS)
    _state["done"] = True


def ensure_default() -> None:
    """The library's default (module docstring): on, once per process, unless off
    or the program chose its own directory."""
    if _state["done"] or _state["disabled"]:
        return
    if jax.config.jax_compilation_cache_dir:  # the program's own choice
        _state["done"] = True
        return
    enable_compilation_cache()


def disable() -> None:
    """Turn the persistent cache off for the rest of the process."""
    _state["disabled"] = True
    jax.config.update("jax_compilation_cache_dir", None)


def program_directory() -> str:
    """Where traced programs are kept
    (:mod:`jaxcal.calibrators.programs.on_disk`): ``jaxcal-programs`` inside the active
    compilation cache directory (JAX's cache reads only its own files there)."""
    return os.path.join(jax.config.jax_compilation_cache_dir or directory(),
                        "jaxcal-programs")  # fmt: skip


def private_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` (an existing file or directory) is not private to this user, or
    ``None`` when it is: it must be owned by this user and not writable by its group
    or others, and no folder above it may let others replace it (group/world-
    writable without the sticky bit, as ``/tmp`` has).

    Raises:
        OSError: ``path`` cannot be read.
    """
    path = os.path.abspath(path)
    info = os.stat(path)
    uid = os.getuid()
    if info.st_uid != uid:
        return f"it is owned by user id {info.st_uid}, not by this user ({uid})"
    mode = stat.S_IMODE(info.st_mode)
    if mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"it is writable by other users (mode {mode:o}; expected 700)"
    parent = os.path.dirname(path)
    while parent and parent != path:
        mode = os.stat(parent).st_mode
        if mode & (stat.S_IWGRP | stat.S_IWOTH) and not mode & stat.S_ISVTX:
            return (
                f"the folder {parent} above it is writable by other users without "
                f"the sticky bit (mode {stat.S_IMODE(mode):o}): they could replace it"
            )
        path, parent = parent, os.path.dirname(parent)
    return None


def warn_bypassed(path: str | os.PathLike, problem: str, stacklevel: int = 2) -> None:
    """The one warning of an on-disk cache folder that is not used (``problem``:
    :func:`private_problem`'s reason)."""
    warnings.warn(
        f"jaxcal: the cache folder {path} is not used, {problem}; anyone who can "
        "write there could make jaxcal run their code. Running without the on-disk "
        "cache: make it yours alone (chmod 700, owned by you), or set "
        "JAXCAL_CACHE_DIR to a private folder (JAXCAL_CACHE=0 turns the cache off)",
        stacklevel=stacklevel + 1,
    )


def is_enabled() -> bool:
    """True when compiled programs are read from and written to disk."""
    return bool(jax.config.jax_compilation_cache_dir) and not _state["disabled"]


@functools.cache
def _glibc(name: str) -> Callable | None:
    """glibc's function ``name``, or None elsewhere (musl, macOS: nothing to do)."""
    try:
        return getattr(ctypes.CDLL("libc.so.6"), name)
    except (OSError, AttributeError):
        return None


def return_freed_heap() -> None:
    """Give the heap freed since the last call back to the system (glibc keeps it).

    XLA:CPU's load of a large program (the turbofan's Newton solve under ``jacfwd``:
    813 kernels) allocates ~1.3 GB that it frees at once, and glibc keeps the freed
    pages in the process: 0.5-0.65 GB of resident memory per program that the rest
    of a diagnosis never reused, so its peak rose by as much (NASA FD001's whole
    diagnosis: 2.97 GB peak before, 2.47 GB after). Called after a kept program's
    first call (:func:`jaxcal.calibrators.programs.on_disk.kept`); it moves no number (a
    trim at the end of each diagnosis stage as well gained 0.02 GB: not done)."""
    trim = _glibc("malloc_trim")
    if trim is not None:
        trim(0)


MMAP_THRESHOLD = 8 << 20  # bytes: an array this large gets a mapping of its own
_M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number


def map_large_arrays(threshold: int = MMAP_THRESHOLD) -> bool:
    """Allocate blocks of at least ``threshold`` bytes as mappings of their own,
    given back to the system as they are freed (glibc's ``mallopt``; elsewhere
    nothing is done and False returned).

    glibc raises this threshold, up to 32 MB, each time a mapped block is freed, and
    blocks below it come from the heap, which keeps the pages freed in the middle.
    A fleet's arrays are a few MB each (NASA FD002's 53,759 rows by 14 outputs: 6
    MB), made and dropped at every step of a fit, so the heap grows with them: the
    whole FD002 diagnosis peaked at 1.92-1.93 GB resident with the moving threshold
    and 1.80 GB at a fixed 8 MB, 10-20 s slower (``results/loop/profile.md`` round
    15; at 1 MB, 40 s slower: every array faulted in afresh). A process setting, so
    called at a command line's entry (``python -m jaxcal.diagnose``); no number
    moves."""
    if threshold <= 0:
        raise ValueError(f"map_large_arrays: threshold > 0 bytes, got {threshold}")
    mallopt = _glibc("mallopt")
    return mallopt is not None and bool(mallopt(_M_MMAP_THRESHOLD, int(threshold)))
