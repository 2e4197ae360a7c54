"""A run's own model: what a run folder keeps of it, and how a run loads it again.

A run calibrates with the model it was trained on, not with whatever its ``model=``
spec names later, and it never imports a path outside its folder. What the training
job stores (``data.json`` ``"model_source"``), by the kind of spec:

* ``file.py:attr`` (``"file"``): a copy of the file, ``<run>/model/<file name>``, and
  its sha256. The run loads that copy, from the bytes whose hash it checks (an
  edited copy is refused), so it loads after the original moved and does not follow
  later edits of it. Only that one file is copied: modules it imports are not.
* a registered name (``"registered"``, e.g. ``cmapss``, ``heat_exchanger``): the
  name and the jaxcal version; the installed jaxcal's model is loaded, with a
  warning when the version differs.
* ``package.module:attr`` (``"module"``): the module name, and the sha256 of its
  source file. It loads only with the user's consent: the same ``module:attr``
  named by the user in this process (then nothing new is imported), or
  ``trust_code=True`` (imported by name, as Python finds it), with a warning when
  its source changed since training.
* an ``extended_model.json`` of the diagnosis (``"extended"``): a copy of the file
  and its sha256, with its base model stored by the same rules (a base file copied
  beside it), so the extension loads from the run alone.

A model that cannot be loaded again (an attribute of ``__main__``, a module without
a source file) is refused before the run folder is created. A ``data.json`` of the
older layout (a bare ``model_spec``) still loads a registered or module model; one
naming a file outside the folder is refused, as loading it would run that file:
:func:`adopt_model_file` copies a file you trust into the run.

What a run says is data, its model copy code (``docs/trust.md``): a copy runs only
with the user's consent (:mod:`jaxcal.trust`): ``trust_code=True``, or the same file
(same bytes and attribute) named by the user in this process, e.g. trained on in this
session. Without it the load is refused with an error naming the copy and the flag.
A run never makes jaxcal import a module from the working directory or ``sys.path``
on its own say-so, nor call any function but the one its consented copy names.
:mod:`jaxcal.calibrators.methods.policy.run_model` compares a model passed to a run with
the run's own.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import json
import os
import re
import sys
import types
import warnings
from pathlib import Path
from typing import NamedTuple

from jaxcal import trust
from jaxcal.model import Model
from jaxcal.models import available, load
from jaxcal.models.extended import Added, build_extended, resolve_base
from jaxcal.runs.atomic import write_atomic
from jaxcal.runs.folder import DATA_FILE, read_json, write_json
from jaxcal.runs.lock import hold_run
from jaxcal.version import __version__

SOURCE_DIR = "model"  # the copy of a file model, inside the run folder
_IDENTIFIER = re.compile(r"[A-Za-z_]\w*")
_MODULE = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")


class ModelSource(NamedTuple):
    """What a run stores of its model.

    Attributes:
        record: the ``data.json`` ``"model_source"`` entry.
        content: the file's bytes to copy (kind ``"file"``), else ``None``.
    """

    record: dict
    content: bytes | None = None
    extra: tuple = ()  # more (record, content) pairs to write (an extension's base)


def _sha256(content: bytes) -> str:
    return hashlib.sha256(content).hexdigest()


def _is_file_spec(where: str) -> bool:
    # the rule jaxcal.models.load applies to tell a file from a module
    return where.endswith(".py") or os.sep in where


def model_source(spec: str) -> ModelSource:
    """What a run of the model ``spec`` (a ``jaxcal.models.load`` spec) stores.

    Writes nothing; the model must already have loaded from ``spec``.

    Raises:
        ValueError: naming ``model=`` when the model cannot be loaded again from what
            a run can store (defined in ``__main__`` or a module with no file).
    """
    if spec in available():
        return ModelSource({"kind": "registered", "name": spec, "version": __version__})
    if spec.endswith(".json"):
        return _extended_source(spec)
    where, _, attr = spec.rpartition(":")
    if _is_file_spec(where):
        path = Path(where).absolute()
        try:
            content = path.read_bytes()
        except OSError as err:
            raise ValueError(f"model={spec!r}: cannot read {path} ({err})") from None
        record = {
            "kind": "file",
            "file": f"{SOURCE_DIR}/{path.name}",
            "attr": attr,
            "sha256": _sha256(content),
            "origin": str(path),
        }
        return ModelSource(record, content)
    module = sys.modules.get(where) or importlib.import_module(where)
    origin = getattr(module, "__file__", None)
    if where == "__main__" or not origin or not os.path.isfile(origin):
        raise ValueError(
            f"model={spec!r}: a run must load its model again, and {where} has no "
            "source file it could copy or import by name; put the model in a file "
            "and pass model=path/to/file.py:attr"
        )
    record = {
        "kind": "module",
        "module": where,
        "attr": attr,
        "sha256": _sha256(Path(origin).read_bytes()),
        "origin": origin,
    }
    return ModelSource(record)


def _extended_source(spec: str) -> ModelSource:
    """An extended model: its JSON copied (the base rewritten to the run's own
    copy of it) and the base stored by the rules of :func:`model_source`."""
    path = Path(spec).absolute()
    try:
        ext = json.loads(path.read_text())
        base_spec = resolve_base(ext, str(path))
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(
            f"model={spec!r}: not a readable extended model ({err})"
        ) from None
    base = model_source(base_spec)
    if base.record["kind"] == "file":  # the copy's name, relative to the JSON copy
        ext["base"] = f"{Path(base.record['file']).name}:{base.record['attr']}"
    elif base.record["kind"] == "registered":
        ext["base"] = base.record["name"]
    content = (json.dumps(ext, indent=1) + "\n").encode()
    record = {
        "kind": "extended",
        "file": f"{SOURCE_DIR}/{path.name}",
        "sha256": _sha256(content),
        "origin": str(path),
        "base": base.record,
    }
    extra = ((base.record, base.content),) if base.content is not None else ()
    return ModelSource(record, content, extra + base.extra)


def check_source_unchanged(run_dir: str | os.PathLike, source: ModelSource) -> None:
    """A resumed run must train on the model it started with.

    Args:
        run_dir: the run folder (a new one, or one of the older layout: nothing to
            compare).
        source: :func:`model_source` of the model given now.

    Raises:
        ValueError: the model's source changed since the run started.
    """
    path = Path(run_dir) / DATA_FILE
    stored = read_json(path).get("model_source") if path.is_file() else None
    if not stored or stored.get("sha256") in (None, source.record.get("sha256")):
        return
    raise ValueError(
        f"run {run_dir} started on {stored.get('origin')} (sha256 "
        f"{stored['sha256'][:12]}...); {source.record.get('origin')} now has sha256 "
        f"{str(source.record.get('sha256'))[:12]}...: a resume would train the policy "
        "on another model; choose another name= (output.name=) or restore the file"
    )


def store_model_source(run_dir: str | os.PathLike, source: ModelSource) -> dict:
    """Write the copy of a file model into ``run_dir`` (atomically); returns the
    record to put in ``data.json``."""
    if source.content is not None:
        write_atomic(Path(run_dir) / source.record["file"], source.content)
    for record, content in source.extra:
        write_atomic(Path(run_dir) / record["file"], content)
    return source.record


def _from_attr(obj, attr: str, where: str) -> Model:
    model = obj() if callable(obj) and not isinstance(obj, Model) else obj
    if not isinstance(model, Model):
        raise ValueError(
            f"{where}: {attr!r} is neither a jaxcal.Model nor a callable returning one"
        )
    return model


def _copy_path(run_dir: Path, record: dict) -> Path:
    """The copy's path, refused unless it lies inside ``run_dir``."""
    name = str(record.get("file", ""))
    path = (run_dir / name).resolve()
    inside = run_dir.resolve() in path.parents
    if not name or os.path.isabs(name) or ".." in Path(name).parts or not inside:
        raise ValueError(
            f"run {run_dir}: data.json names the model copy {name!r}, which is not a "
            "file inside the run folder; a run never imports a path outside it"
        )
    return path


def _load_copy(run_dir: Path, record: dict, trust_code: bool) -> Model:
    path = _copy_path(run_dir, record)
    attr = str(record.get("attr", ""))
    if not _IDENTIFIER.fullmatch(attr):
        raise ValueError(f"run {run_dir}: data.json names the attribute {attr!r}")
    try:
        content = path.read_bytes()
    except OSError as err:
        raise ValueError(f"run {run_dir}: cannot read its model copy ({err})") from None
    digest = _sha256(content)
    if digest != record.get("sha256"):
        raise ValueError(
            f"run {run_dir}: its model copy {path} has sha256 {digest[:12]}..., not "
            f"the {str(record.get('sha256'))[:12]}... it was trained on: the copy was "
            "edited after training; restore it or retrain the run"
        )
    what = f"run {run_dir}: its model copy {path} ({attr})"
    trust.require_consent(content, attr, what, trust_code)
    # Run from the bytes just hashed (no import machinery: no stale bytecode, no
    # __pycache__ written into the run), under a module name of its own.
    name = f"_jaxcal_run_model_{digest[:16]}"
    module = types.ModuleType(name)
    module.__file__ = str(path)
    sys.modules[name] = module  # dataclasses and pickling look the module up
    try:
        exec(compile(content, str(path), "exec"), module.__dict__)  # noqa: S102
        if not hasattr(module, attr):
            raise ValueError(f"{path} has no attribute {attr!r}")
        return _from_attr(getattr(module, attr), attr, str(path))
    except Exception as err:  # the user's code: whatever it raises, name the run
        sys.modules.pop(name, None)
        raise ValueError(
            f"run {run_dir}: its model copy {path} failed to load: "
            f"{type(err).__name__}: {err}"
        ) from err


def _changed(what: str, run_dir: Path, detail: str) -> None:
    warnings.warn(
        f"run {run_dir} was trained with {what}; {detail}: the policy may no longer "
        "fit the model (retrain the run, or install what it was trained with)",
        stacklevel=4,
    )


def load_run_model(
    run_dir: str | os.PathLike, data: dict, *, trust_code: bool = False
) -> Model:
    """The model of a run folder (its ``data.json`` ``data``); see the module
    docstring for what is loaded and when it warns.

    Args:
        run_dir: the run folder.
        data: its parsed ``data.json``.
        trust_code: the user's consent to run the run's model copy or module
            (:mod:`jaxcal.trust`); a registered model needs none.

    Raises:
        ValueError: the copy is missing, outside the folder or edited, the record is
            malformed, or (older layout) the model is a file outside the folder;
            :class:`~jaxcal.trust.UntrustedCodeError` (a ValueError) naming the
            copy or module and the flag when it needs the user's consent.
    """
    run_dir = Path(run_dir)
    record = data.get("model_source")
    if record is None:
        spec = str(data.get("model_spec", data.get("engine")))
        return _load_legacy(run_dir, spec, trust_code)
    if not isinstance(record, dict):
        raise ValueError(
            f"run {run_dir}: data.json's model_source is {record!r}, not an object"
        )
    kind = record.get("kind")
    if kind == "file":
        return _load_copy(run_dir, record, trust_code)
    if kind == "extended":
        return _load_extended(run_dir, record, trust_code)
    if kind == "registered" and record.get("name") in available():
        if record.get("version") != __version__:
            _changed(f"jaxcal {record.get('version')}'s {record['name']!r}", run_dir,
                     f"this is jaxcal {__version__}")  # fmt: skip
        return load(record["name"])
    module, attr = str(record.get("module")), str(record.get("attr"))
    if kind == "module" and _MODULE.fullmatch(module) and _IDENTIFIER.fullmatch(attr):
        _module_consent(run_dir, module, attr, trust_code)
        model = load(f"{module}:{attr}")  # a module name: never a path
        origin = getattr(sys.modules.get(module), "__file__", None)
        digest = _sha256(Path(origin).read_bytes()) if origin else None
        if digest != record.get("sha256"):
            _changed(f"{module} of sha256 {str(record.get('sha256'))[:12]}...",
                     run_dir, f"the installed {origin} differs")  # fmt: skip
        return model
    raise ValueError(
        f"run {run_dir}: data.json's model_source {record!r} is not a model this "
        f"jaxcal can load (a file copy in {SOURCE_DIR}/, a registered name "
        f"{list(available())} or a module name)"
    )


def _module_consent(run_dir: Path, module: str, attr: str, trust_code: bool) -> None:
    """A run's module model loads with ``trust_code``, or when the user named the
    same ``module:attr`` in this process (already imported: nothing is searched
    for on ``sys.path``, the working directory included, on the run's say-so)."""
    if trust_code:
        return
    origin = getattr(sys.modules.get(module), "__file__", None)
    content = Path(origin).read_bytes() if origin and os.path.isfile(origin) else b""
    what = f"run {run_dir}: its model, the module {module}:{attr},"
    trust.require_consent(content, f"{module}:{attr}", what, trust_code)


def _load_extended(run_dir: Path, record: dict, trust_code: bool) -> Model:
    """An extension from its checked copy, over its base loaded from the run."""
    path = _copy_path(run_dir, record)
    content = path.read_bytes()
    if _sha256(content) != record.get("sha256"):
        raise ValueError(
            f"run {run_dir}: its extended-model copy {path} was edited after training"
        )
    ext = json.loads(content)
    base_record = {"model_source": record.get("base")}
    base = load_run_model(run_dir, base_record, trust_code=trust_code)
    return build_extended(base, ext["declared"], [Added(**a) for a in ext["added"]])


def recorded_source(data: dict) -> dict | None:
    """The ``"model_source"`` of a ``data.json`` dict; for the older layout naming a
    registered model, its name (no version: it was not recorded)."""
    if "model_source" in data:
        return data["model_source"]
    spec = str(data.get("model_spec", data.get("engine")))
    return {"kind": "registered", "name": spec} if spec in available() else None


def _load_legacy(run_dir: Path, spec: str, trust_code: bool) -> Model:
    where, sep, _ = spec.rpartition(":")
    if sep and _is_file_spec(where):
        raise ValueError(
            f"run {run_dir} has no copy of its model (written before runs kept one): "
            f"its data.json names {where}, outside the run folder, and loading it "
            "would run that file. If you trust it: jaxcal.deploy.adopt_model_file("
            f"{str(run_dir)!r}, {where!r}) copies it into the run; else retrain"
        )
    if spec in available():
        return load(spec)
    attr = spec.rpartition(":")[2]
    if sep and _MODULE.fullmatch(where) and _IDENTIFIER.fullmatch(attr):
        _module_consent(run_dir, where, attr, trust_code)
        return load(spec)
    raise ValueError(f"run {run_dir}: data.json names no loadable model ({spec!r})")


def adopt_model_file(run_dir: str | os.PathLike, path: str | os.PathLike) -> Model:
    """Give a run of the older layout (its model a file outside the folder) a copy
    of ``path``, a file you trust to be the model it was trained on.

    Returns:
        The model, loaded from the new copy.

    Raises:
        ValueError: the run's model is not a file, or the copy does not load.
        RunInUseError: a training holds the run.
    """
    run_dir = Path(run_dir)
    data = read_json(run_dir / DATA_FILE)
    where, sep, attr = str(data.get("model_spec", "")).rpartition(":")
    if "model_source" in data or not (sep and _is_file_spec(where)):
        raise ValueError(
            f"run {run_dir} does not name a model file outside it: nothing to adopt"
        )
    source = model_source(f"{Path(path).absolute()}:{attr}")
    with hold_run(run_dir):
        store_model_source(run_dir, source)
        model = _load_copy(run_dir, source.record, trust_code=True)  # named by you
        write_json(run_dir / DATA_FILE, {**data, "model_source": source.record})
    return model
