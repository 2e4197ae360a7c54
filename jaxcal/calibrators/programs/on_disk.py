"""Traced calibrator programs, kept on disk as exported StableHLO.

JAX's persistent compilation cache (:mod:`jaxcal.cache`) spares a new process the
XLA compilation, but not the tracing that comes before it: to find the cached
executable, JAX first traces the Python function into a jaxpr and lowers it, which
for a model with an iterative solver (the turbofan's Newton solve batched over sigma
points and units) takes far longer than the compute. ``jax.export`` serialises a
traced and lowered program; a later process deserialises it (milliseconds) and
compiles it, which the persistent cache then answers.

A program on disk is keyed by what it was traced from: the model, named by jaxcal's
source for the built-in models (``Model.origin``, set by :func:`jaxcal.models.load`)
or by the digest of a user model's own jaxprs
(:mod:`~jaxcal.calibrators.programs.traced_key`; a model whose jaxpr hides behaviour has
none and is traced again in each process); jaxcal's source (every file of the package,
hashed once per process), the JAX version, the problem's names and fixed values, the
method's settings, the float type and the arguments' shapes.

The directory is the cache's (``jaxcal-programs`` inside the compilation cache
directory, by default ``~/.cache/jaxcal/xla/jaxcal-programs``), on and off with it
(``JAXCAL_CACHE=0``). A program there is code the process runs, so it is read only
from a folder and a file private to this user (:func:`jaxcal.cache.private_problem`:
owned by the user, writable by no one else): otherwise the program is run as traced,
without the disk, with one warning naming the folder (a planted program could return
wrong numbers without a word). A file that cannot be read is traced again and
rewritten; at most :data:`MAX_KEPT` programs and :data:`MAX_BYTES` of them are kept,
the least recently used removed first.

In a ``jax.distributed`` cluster, JAX writes its persistent cache from process 0 only
(``jax._src.compiler._cache_write``), and a CPU executable is keyed by the device it
runs on, so every other process would compile each program in every run. Such a
process keeps the compiled executable itself, beside the program, keyed by its place in
the cluster (:func:`_compiled_here`); the same privacy rule covers it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import warnings
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
from jax import export
from jax.experimental import serialize_executable

from jaxcal import cache
from jaxcal.calibrators.interface import CalOutput
from jaxcal.runs.atomic import write_atomic

SUFFIX = ".jaxexport"
EXECUTABLE_SUFFIX = ".jaxexe"  # a cluster process's own compiled executable
# Programs kept at most, and their bytes; past either the least recently used go (a
# new jaxcal source or JAX version keys new files, so old ones would otherwise pile
# up). A user's model keys programs of its own (6-90 kB for the tests' small
# models): at 64 programs the suite's few hundred evicted each other, and the
# turbofan's, on every run, so each was exported (traced and lowered) again.
MAX_KEPT = 4096
MAX_BYTES = 512 * 2**20


_SERIALISABLE: set[type] = set()


def serialisable(cls: type) -> type:
    """Register a named tuple that programs take or return for serialisation
    (once per class; usable as a decorator)."""
    if cls not in _SERIALISABLE:
        export.register_namedtuple_serialization(
            cls, serialized_name=f"{cls.__module__}.{cls.__qualname__}"
        )
        _SERIALISABLE.add(cls)
    return cls


serialisable(CalOutput)


# the jaxcal package: a kept program is stale once any of its code or constants changes
PACKAGE_ROOT = Path(__file__).resolve().parents[2]


@functools.cache
def source_digest() -> str:
    """sha256 of every file of the jaxcal package (code and stored constants)."""
    root = PACKAGE_ROOT
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        if path.is_file() and path.suffix in (".py", ".json"):
            digest.update(str(path.relative_to(root)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def kept(fn: Callable, key: tuple | None) -> Callable:
    """``fn`` (jitted), run from a program kept on disk under ``key`` (one file per
    argument signature), or ``fn`` itself when ``key`` is None or the cache is off.

    Args:
        fn: the jitted program.
        key: what the program depends on besides its arguments' shapes (``repr``-
            stable across processes), or None (not kept).
    """
    if key is None:
        return fn
    calls = {}  # argument signature -> the compiled call of its exported program

    def run(*args):
        if not cache.is_enabled():
            return fn(*args)
        leaves, tree = jax.tree.flatten(args)
        signature = (str(tree),) + tuple((np.shape(a), _dtype_name(a)) for a in leaves)
        call = calls.get(signature)
        if call is not None:
            return call(*args)
        call = calls[signature] = _exported(fn, key, signature, args)
        out = call(*args)  # compiles or loads the executable, then dispatches
        cache.return_freed_heap()
        return out

    return run


def _dtype_name(leaf) -> str:
    """A leaf's dtype name; read from ``.dtype`` when it has one (``np.result_type``
    of a jax array is deprecated: a DeprecationWarning, an error under -W error)."""
    dtype = getattr(leaf, "dtype", None)
    return np.dtype(dtype).name if dtype is not None else np.result_type(leaf).name


_BYPASSED: set[str] = set()  # program folders already warned about: one warning each


def _not_private(path: Path) -> str | None:
    """Why the program folder, or the program file ``path`` in it, is not this
    user's alone (:func:`jaxcal.cache.private_problem`), or ``None``."""
    try:
        for where in (path.parent, path):
            if where.exists():
                problem = cache.private_problem(where)
                if problem is not None:
                    return problem if where == path.parent else f"{path}: {problem}"
    except OSError as err:
        return f"it cannot be read ({err})"
    return None


def _exported(fn: Callable, key: tuple, signature: tuple, args) -> Callable:
    """The jitted call of ``fn``'s exported program, read from disk or exported and
    written there; ``fn`` itself when the program folder is not private."""
    text = repr((key, signature, source_digest(), jax.__version__))
    name = hashlib.sha256(text.encode()).hexdigest()[:32] + SUFFIX
    path = Path(cache.program_directory()) / name
    problem = _not_private(path)
    if problem is not None:
        if str(path.parent) not in _BYPASSED:
            _BYPASSED.add(str(path.parent))
            cache.warn_bypassed(path.parent, problem, stacklevel=4)
        return fn
    exp = None
    if path.is_file():
        try:
            exp = export.deserialize(bytearray(path.read_bytes()))
            os.utime(path)  # recently used: kept by _prune
        except Exception as err:  # noqa: BLE001 - a damaged file is traced again
            warnings.warn(f"{path}: unreadable ({err}); traced again", stacklevel=3)
    if exp is None:
        try:
            exp = export.export(fn)(*args)
            data = bytes(exp.serialize())
        except Exception as err:  # noqa: BLE001 - not keepable: run it as it is
            warnings.warn(f"program not kept on disk: {err}", stacklevel=3)
            return fn
        os.makedirs(path.parent, mode=0o700, exist_ok=True)
        write_atomic(path, data)
        _prune(path.parent)
    if jax.process_index() != 0:
        return _compiled_here(exp, path, args)
    return jax.jit(exp.call)


def _compiled_here(exp: export.Exported, path: Path, args) -> Callable:
    """The compiled executable of ``exp`` for a cluster process other than the
    first (module docstring), read from beside the program ``path`` or compiled and
    written there. ``jax.jit`` of the program when it cannot be kept, or for
    arguments the executable was not compiled for."""
    jitted = jax.jit(exp.call)
    devices = jax.local_devices()
    place = f"p{jax.process_index()}of{jax.process_count()}"
    place += "d" + "-".join(str(d.id) for d in devices)
    exe = path.with_name(f"{path.name[: -len(SUFFIX)]}-{place}{EXECUTABLE_SUFFIX}")
    lowered = jitted.lower(*args)  # the program's own StableHLO: no model traced
    compiled = None
    if exe.is_file() and _not_private(exe) is None:
        try:
            compiled = serialize_executable.deserialize_and_load(
                exe.read_bytes(),
                lowered.in_tree,
                lowered.out_tree,
                execution_devices=devices,
            )
            os.utime(exe)
        except Exception as err:  # noqa: BLE001 - a damaged file: compiled again
            warnings.warn(f"{exe}: unreadable ({err}); compiled again", stacklevel=4)
    if compiled is None:
        compiled = lowered.compile()
        try:
            write_atomic(exe, serialize_executable.serialize(compiled)[0])
            _prune(exe.parent)
        except Exception as err:  # noqa: BLE001 - not keepable: run it as it is
            warnings.warn(f"executable not kept on disk: {err}", stacklevel=4)

    def call(*call_args):
        try:
            return compiled(*call_args)
        except TypeError:  # arguments of other types (weak or not): JAX's own call
            return jitted(*call_args)

    return call


def _prune(directory: Path, keep: int = MAX_KEPT, max_bytes: int = MAX_BYTES) -> None:
    """Keep only the most recently used programs in ``directory``: at most ``keep``
    of them and ``max_bytes`` together."""
    files = []
    for f in [*directory.glob("*" + SUFFIX), *directory.glob("*" + EXECUTABLE_SUFFIX)]:
        try:
            stat = f.stat()
        except OSError:  # removed meanwhile by another process
            continue
        files.append((stat.st_mtime, stat.st_size, f))
    total = 0
    for rank, (_, size, f) in enumerate(sorted(files, reverse=True)):
        total += size
        if rank >= keep or total > max_bytes:
            f.unlink(missing_ok=True)
