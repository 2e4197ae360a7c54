"""Settings: ``key=value`` overrides for frozen dataclass configs, and their JSON.

The CLIs take arguments such as ``dataset=cmapss agent=lac agent.actor_lr=3e-4 seed=3
theta=HPC_eff_mod,HPC_flow_mod`` (the jumanji / Hydra grammar, STYLE §2.6) without a
Hydra dependency. Group keys (``agent=lac``) replace a sub-config with a named preset
from a registry; dotted keys override one field of a nested frozen dataclass through
``dataclasses.replace``; values are coerced to the field's annotated type. Group choices
are applied before field overrides, whatever their order on the command line, so
``agent.actor_lr=1e-3 agent=lac`` means "LAC with that learning rate". Every mistake
(unknown key, token without ``=``, a value of the wrong type) is a ``ValueError`` whose
message names the key and the accepted form; the CLIs print it and exit with code 2.

``config_to_dict`` / ``config_from_dict`` give the JSON round trip used for a run's
``config.json``. Each dataclass is written with a ``"_type"`` entry (its class name), so
a field annotated with a union of configs (``SACConfig | LACConfig``) restores to the
right one. ``check_output_path`` checks that an output file or folder can be written,
so that a command refuses a bad ``out=`` before any long work. A library module (configs
are read and stored by the training job, the paper pipeline, the diagnosis): the
command-line front itself (help, usage, exit codes) is :mod:`jaxcal.cli.args`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any

_TRUE = frozenset({"true", "1", "yes", "on"})
_FALSE = frozenset({"false", "0", "no", "off"})
_NONE = frozenset({"none", "null"})
TYPE_KEY = "_type"


class UnknownKeyError(ValueError):
    """A ``key=value`` key that names nothing: the message lists the valid keys, and
    ``key`` / ``valid`` carry them so that a command line can suggest the closest
    (:mod:`jaxcal.cli.args`)."""

    def __init__(self, message: str, key: str, valid: Sequence[str]):
        super().__init__(message)
        self.key = key
        self.valid = tuple(valid)


def _field_types(cfg_or_cls: Any) -> dict[str, Any]:
    """Resolved annotations of a dataclass' init fields (handles string annotations)."""
    cls = cfg_or_cls if isinstance(cfg_or_cls, type) else type(cfg_or_cls)
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def _union_args(tp: Any) -> tuple[Any, ...] | None:
    """Members of ``Union[...]`` / ``X | Y``, or None when ``tp`` is not a union."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return typing.get_args(tp)
    return None


def coerce(text: str, tp: Any, key: str) -> Any:
    """Convert one command-line string to the annotated type ``tp``.

    Supported: ``bool`` (true/false/1/0/yes/no/on/off), ``int``, ``float`` (not
    NaN), ``str``, ``Literal[...]``, ``Optional[X]`` (``none``/``null``),
    ``tuple[X, ...]`` and fixed-length ``tuple[X, Y]`` from comma-separated lists (an
    empty value is ``()``).

    Raises:
        ValueError: naming ``key`` and the expected form when ``text`` does not fit.
    """
    members = _union_args(tp)
    if members is not None:
        if type(None) in members and text.strip().lower() in _NONE:
            return None
        others = [m for m in members if m is not type(None)]
        for member in others:
            try:
                return coerce(text, member, key)
            except ValueError:
                continue
        raise ValueError(f"{key}={text!r}: expected one of {tp} (or none)")
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        choices = typing.get_args(tp)
        for choice in choices:
            if str(choice) == text:
                return choice
        raise ValueError(
            f"{key}={text!r}: expected one of {', '.join(map(str, choices))}"
        )
    if origin is tuple or tp is tuple:
        args = typing.get_args(tp)
        parts = [p.strip() for p in text.split(",")] if text.strip() else []
        if not args or (len(args) == 2 and args[1] is Ellipsis):
            item = args[0] if args else str
            return tuple(coerce(p, item, key) for p in parts)
        if len(parts) != len(args):
            raise ValueError(
                f"{key}={text!r}: expected {len(args)} comma-separated values"
            )
        return tuple(coerce(p, a, key) for p, a in zip(parts, args, strict=True))
    if tp is bool:
        low = text.strip().lower()
        if low in _TRUE or low in _FALSE:
            return low in _TRUE
        raise ValueError(f"{key}={text!r}: expected a bool (true/false)")
    if tp is int:
        try:
            return int(text)
        except ValueError:
            try:
                value = float(text)  # accept 1e6 for counts, but only if integral
            except ValueError:
                value = math.nan
            if math.isfinite(value) and value.is_integer():
                return int(value)
            raise ValueError(f"{key}={text!r}: expected an integer") from None
    if tp is float:
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"{key}={text!r}: expected a number") from None
        if math.isnan(value):
            raise ValueError(f"{key}={text!r}: NaN is not a valid setting")
        return value
    if tp is str or tp is Any:
        return text
    raise ValueError(f"{key}: fields of type {tp} cannot be set from the command line")


def _set_path(
    cfg: Any, path: Sequence[str], text: str | None, value: Any = None, prefix: str = ""
) -> Any:
    """``cfg`` with the field at ``path`` replaced (``text`` coerced when given)."""
    name, rest = path[0], path[1:]
    full = prefix + name
    ftypes = _field_types(cfg)
    if name not in ftypes:
        raise UnknownKeyError(
            f"unknown key {prefix + '.'.join(path)!r}; valid keys"
            f"{' of ' + prefix[:-1] if prefix else ''} ({type(cfg).__name__}): "
            + ", ".join(sorted(ftypes)),
            key=prefix + ".".join(path),
            valid=[prefix + n for n in sorted(ftypes)],
        )
    current = getattr(cfg, name)
    if rest:
        if not dataclasses.is_dataclass(current):
            raise ValueError(
                f"{full!r} is a plain value, not a config; cannot set "
                f"{prefix + '.'.join(path)!r}"
            )
        new = _set_path(current, rest, text, value, prefix=full + ".")
        return dataclasses.replace(cfg, **{name: new})
    if text is None:
        return dataclasses.replace(cfg, **{name: value})
    if dataclasses.is_dataclass(current):
        valid = ", ".join(sorted(_field_types(current)))
        raise ValueError(
            f"{full!r} is a nested config without presets; set its fields as "
            f"{full}.<field>=<value> (fields: {valid})"
        )
    return dataclasses.replace(cfg, **{name: coerce(text, ftypes[name], full)})


def parse_overrides(
    argv: Sequence[str],
    base: Any,
    groups: Mapping[str, Mapping[str, Any]] | None = None,
) -> Any:
    """Apply ``key=value`` tokens to a frozen dataclass config.

    Args:
        argv: tokens such as ``["agent=lac", "agent.actor_lr=3e-4", "seed=3"]``.
        base: the default root config (a frozen dataclass instance).
        groups: preset registries by (possibly dotted) field path, e.g.
            ``{"agent": AGENTS, "dataset": DATASETS}``; ``agent=lac`` sets
            ``base.agent = AGENTS["lac"]``.

    Returns:
        A new config; ``base`` is not modified.

    Raises:
        ValueError: malformed token, duplicate key, unknown key (the message lists
            the valid keys), unknown preset (lists the presets) or a badly typed value.
    """
    groups = dict(groups or {})
    seen: dict[str, str] = {}
    for token in argv:
        key, sep, text = token.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"malformed argument {token!r}: expected key=value")
        if key in seen:
            raise ValueError(f"key {key!r} given twice ({seen[key]!r} and {text!r})")
        seen[key] = text
    cfg = base
    # Presets first, so that dotted overrides refine the chosen preset.
    for key in sorted((k for k in seen if k in groups), key=lambda k: k.count(".")):
        presets = groups[key]
        if seen[key] not in presets:
            raise ValueError(
                f"unknown {key} {seen[key]!r}; choose one of: " + ", ".join(presets)
            )
        cfg = _set_path(cfg, key.split("."), None, presets[seen[key]])
    for key, text in seen.items():
        if key in groups:
            continue
        try:
            cfg = _set_path(cfg, key.split("."), text)
        except ValueError as err:
            if isinstance(err, UnknownKeyError) and "." not in key and groups:
                raise UnknownKeyError(
                    f"{err} (keys with presets: {', '.join(sorted(groups))})",
                    key=err.key,
                    valid=[*err.valid, *groups],
                ) from None
            raise
    return cfg


def config_to_dict(cfg: Any) -> Any:
    """JSON-ready form of a (nested) dataclass config; tuples become lists."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        out = {TYPE_KEY: type(cfg).__name__}
        for f in dataclasses.fields(cfg):
            if f.init:  # derived (init=False) fields are rebuilt by the constructor
                out[f.name] = config_to_dict(getattr(cfg, f.name))
        return out
    if isinstance(cfg, tuple | list):
        return [config_to_dict(v) for v in cfg]
    if isinstance(cfg, Mapping):
        return {str(k): config_to_dict(v) for k, v in cfg.items()}
    if cfg is None or isinstance(cfg, bool | int | float | str):
        return cfg
    raise ValueError(f"cannot serialise config value {cfg!r} of type {type(cfg)}")


def _from_json(value: Any, tp: Any, key: str) -> Any:
    """Rebuild one field value from its JSON form, guided by the annotation ``tp``."""
    if isinstance(value, dict) and TYPE_KEY in value:
        candidates = _union_args(tp) or (tp,)
        for cand in candidates:
            if dataclasses.is_dataclass(cand) and cand.__name__ == value[TYPE_KEY]:
                return config_from_dict(cand, value)
        raise ValueError(f"{key}: config type {value[TYPE_KEY]!r} does not fit {tp}")
    if value is None:
        return None
    members = _union_args(tp)
    if members is not None:
        tp = next((m for m in members if m is not type(None)), Any)
    if isinstance(value, list):
        args = typing.get_args(tp)
        if args and not (len(args) == 2 and args[1] is Ellipsis):
            return tuple(
                _from_json(v, a, key) for v, a in zip(value, args, strict=True)
            )
        item = args[0] if args else Any
        return tuple(_from_json(v, item, key) for v in value)
    if tp is float and isinstance(value, int):
        return float(value)
    return value


def config_from_dict(cls: type, data: Mapping[str, Any]) -> Any:
    """Inverse of :func:`config_to_dict` for the dataclass ``cls``.

    Fields missing from ``data`` keep their defaults (older config files still load);
    unknown fields or a mismatched ``"_type"`` raise ``ValueError``.
    """
    if TYPE_KEY in data and data[TYPE_KEY] != cls.__name__:
        raise ValueError(f"config is a {data[TYPE_KEY]!r}, expected {cls.__name__!r}")
    ftypes = _field_types(cls)
    unknown = sorted(set(data) - set(ftypes) - {TYPE_KEY})
    if unknown:
        raise ValueError(
            f"unknown fields {unknown} for {cls.__name__}; valid: {sorted(ftypes)}"
        )
    kwargs = {
        name: _from_json(data[name], ftypes[name], name)
        for name in ftypes
        if name in data
    }
    return cls(**kwargs)


def check_output_path(path: str, field: str, *, folder: bool = False) -> str:
    """Check, writing nothing, that ``path`` can be an output file (or folder).

    The nearest existing ancestor of the target's folder must be a writable folder
    (the missing levels are created later); an existing target must be of the right
    kind. Used by the CLIs before any heavy import or long work.

    Args:
        path: the output file (``folder=False``) or folder (``folder=True``).
        field: the setting that named it, for the message (``out``, ``run``, ...).
        folder: whether ``path`` is a folder that files are written into.

    Returns:
        ``path`` unchanged.

    Raises:
        ValueError: naming ``field`` and ``path`` when the path is empty, a folder
            where a file is expected (or the reverse), under a file, or in a folder
            this process may not write.
    """
    kind = "folder" if folder else "file"
    if not path or not path.strip():
        raise ValueError(f"{field}={path!r}: expected a {kind} path, got an empty one")
    full = os.path.abspath(path)
    if folder and os.path.exists(full) and not os.path.isdir(full):
        raise ValueError(f"{field}={path!r} is a file; expected a folder path")
    if not folder and os.path.isdir(full):
        raise ValueError(f"{field}={path!r} is a folder; expected a file path")
    # The folder that receives new entries: the target folder itself, or the file's.
    parent = full if folder else os.path.dirname(full)
    while not os.path.exists(parent) and os.path.dirname(parent) != parent:
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        raise ValueError(
            f"{field}={path!r}: {parent} is a file, so nothing can be created under it"
        )
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(
            f"{field}={path!r}: the folder {parent} is not writable by this user"
        )
    return path
