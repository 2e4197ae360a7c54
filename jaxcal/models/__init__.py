"""The model registry: ``jaxcal.models.load(spec) -> Model``.

``spec`` is a registered name (``"cmapss"``, ``"agtf30"``: the turbofans;
``"heat_exchanger"``: a small static example; ``"thermal"``: a small example with
memory), ``"package.module:attr"`` or
``"path/to/file.py:attr"``, where ``attr`` is a :class:`~jaxcal.model.Model` or a
callable returning one, or an ``extended_model.json`` written by the diagnosis
(:mod:`jaxcal.models.extended`). The command lines take the same spec as ``model=``.

Loading a module or a file runs its code, as unpickling does: load only models you
trust. Naming a file or a module here is the user's consent to run it
(:func:`jaxcal.trust.consent`: a run's copy of the same bytes then loads too); an
``extended_model.json`` whose base is a ``.py`` or a module runs that base only with
``trust_code=True`` or the base named here before (``docs/trust.md``). Whatever goes
wrong in it (a syntax error, an exception at import or in the factory, a missing
attribute, something that is not a model) is a ``ValueError``
naming the spec, the file and the line, so a command line exits 2 with one line.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import os
import sys
import traceback
from collections.abc import Callable

from jaxcal import cache, trust
from jaxcal.model import Model
from jaxcal.models.extended import build_extended, check_base_consent, read_extended
from jaxcal.precision import is_x64

_REGISTRY: dict[str, Callable[[], Model]] = {}
_BUILTIN: dict[str, Callable[[], Model]] = {}  # jaxcal's own factories
_LOADED: dict[tuple[str, bool], Model] = {}  # built-in models, one object each


def register(name: str, factory: Callable[[], Model]) -> None:
    """Make ``load(name)`` return ``factory()`` (a zero-argument callable)."""
    _REGISTRY[name] = factory


def available() -> tuple[str, ...]:
    """The registered model names."""
    return tuple(sorted(_REGISTRY))


def _failure(err: BaseException, spec: str, path: str | None, doing: str) -> str:
    """One line saying what failed in the user's code: file and line of a syntax
    error, else the exception and the deepest line of ``path`` it passed through."""
    if isinstance(err, SyntaxError):
        where = f"{err.filename or path}, line {err.lineno}"
        return f"model={spec!r}: {where}: syntax error: {err.msg}"

    def users(frame) -> bool:  # a line of the user's file, not of this loader
        name = os.path.abspath(frame.filename)
        if path is not None:
            return name == os.path.abspath(path)
        return name != os.path.abspath(__file__)

    frames = [f for f in traceback.extract_tb(err.__traceback__) if users(f)]
    where = f" ({frames[-1].filename}, line {frames[-1].lineno})" if frames else ""
    return f"model={spec!r}: {doing} raised {type(err).__name__}: {err}{where}"


def _from_attr(obj, spec: str, path: str | None) -> Model:
    if isinstance(obj, Model):
        return obj
    got = f"it is a {type(obj).__name__}"
    if callable(obj):
        doing = f"calling {spec.rpartition(':')[2]}()"
        try:
            model = obj()
        except (Exception, SystemExit) as err:  # noqa: BLE001 - the user's code
            raise ValueError(_failure(err, spec, path, doing)) from err
        if isinstance(model, Model):
            return model
        got = f"{doing} returned a {type(model).__name__}"
    raise ValueError(
        f"model={spec!r}: the attribute is neither a jaxcal.Model nor a callable "
        f"returning one ({got})"
    )


def _load_file(path: str, spec: str):
    if not os.path.isfile(path):
        raise ValueError(f"model={spec!r}: file {path} not found")
    name = "_jaxcal_user_model_" + os.path.splitext(os.path.basename(path))[0]
    module_spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module  # dataclasses and pickling look the module up
    try:
        module_spec.loader.exec_module(module)
    except (Exception, SystemExit) as err:  # noqa: BLE001 - the user's code
        del sys.modules[name]  # a half-run module is not kept
        raise ValueError(_failure(err, spec, path, f"running {path}")) from err
    return module


def load(spec: str | Model, *, trust_code: bool = False) -> Model:
    """The model named by ``spec`` (see the module docstring); ``trust_code``: run
    the ``.py`` or module base an ``extended_model.json`` names.

    Raises:
        ValueError: an unknown name, a missing file or attribute, an attribute
            that is not a model (the message lists the registered names), or a
            file or module that fails to run (naming its file and line).
    """
    if isinstance(spec, Model):
        return spec
    spec = str(spec)
    if spec in _REGISTRY and _REGISTRY[spec] is _BUILTIN.get(spec):
        return _builtin(spec)
    if spec in _REGISTRY:
        return _REGISTRY[spec]()
    if spec.endswith(".json"):  # a diagnosis's extended model (models/extended.py)
        if not os.path.isfile(spec):
            raise ValueError(f"model={spec!r}: file not found")
        return load_extended(spec, trust_code=trust_code)
    if ":" not in spec:
        raise ValueError(
            f"model={spec!r}: unknown model; registered: {list(available())}, or "
            "give module:attr or path/to/file.py:attr"
        )
    where, _, attr = spec.rpartition(":")
    if where.endswith(".py") or os.sep in where:
        module = _load_file(where, spec)
    else:
        try:
            module = importlib.import_module(where)
        except ImportError as err:
            raise ValueError(f"model={spec!r}: cannot import {where}: {err}") from err
        except (Exception, SystemExit) as err:  # noqa: BLE001 - the user's code
            raise ValueError(_failure(err, spec, None, f"importing {where}")) from err
    if not hasattr(module, attr):
        raise ValueError(f"model={spec!r}: {where} has no attribute {attr!r}")
    _consent(module, attr if where.endswith(".py") or os.sep in where else spec)
    return _from_attr(getattr(module, attr), spec, getattr(module, "__file__", None))


def _consent(module, name: str) -> None:
    """The user named this module's file (jaxcal.trust): its bytes may load again
    from a run's copy or an extension's base without ``trust_code``."""
    origin = getattr(module, "__file__", None)
    if origin and os.path.isfile(origin):
        with open(origin, "rb") as f:
            trust.consent(f.read(), name)


def _builtin(name: str) -> Model:
    """A built-in model, one object per name and precision (so one set of compiled
    programs), marked as jaxcal's own code (``Model.origin``: its programs are kept
    on disk, :mod:`jaxcal.calibrators.programs.on_disk`). Loading one turns on the
    compilation cache (:mod:`jaxcal.cache`): its set-up compiles too."""
    cache.ensure_default()
    key = (name, is_x64())
    if key not in _LOADED:
        model = _BUILTIN[name]()
        _LOADED[key] = dataclasses.replace(model, origin=f"jaxcal.models:{name}")
    return _LOADED[key]


def _turbofan(name: str) -> Callable[[], Model]:
    def factory() -> Model:
        # lazy: the registry imports a model when it is loaded
        from jaxcal.models.turbofan.model import load_turbofan

        return load_turbofan(name)

    return factory


def _heat_exchanger() -> Model:
    # lazy: the registry imports a model when it is loaded
    from jaxcal.models.heat_exchanger import heat_exchanger_model

    return heat_exchanger_model()


def _thermal() -> Model:
    # lazy: the registry imports a model when it is loaded
    from jaxcal.models.thermal import thermal_model

    return thermal_model()


_BUILTIN.update(
    cmapss=_turbofan("cmapss"), agtf30=_turbofan("agtf30"),
    heat_exchanger=_heat_exchanger, thermal=_thermal,
)  # fmt: skip
_REGISTRY.update(_BUILTIN)

# The built-in models' own data files for a training run: the turbofan's N-CMAPSS
# files, read and generated by its code at the training layer, so named here
# (``module:attr``) and imported by :mod:`jaxcal.training.data.run` when a run reads
# or generates one. ``read(cfg, path, *, units, log, model)`` -> CalibrationData, or
# None for a table; ``generator(name)`` -> ``generate(path, progress)`` -> its line.
TRAINING_FILES = {
    "read": "jaxcal.models.turbofan.training:read_data",
    "generator": "jaxcal.models.turbofan.training:generator",
}

__all__ = ["available", "load", "register"]


def load_extended(path: str, *, trust_code: bool = False) -> Model:
    """The model of a diagnosis's ``extended_model.json`` (:mod:`.extended`): its base
    loaded (a relative ``.py`` base resolved against the file's folder) and the added
    effects put in.

    Args:
        path: the file.
        trust_code: run its base when it is a ``.py`` file or a module (without:
            only a registered name, or a file the user named in this process).

    Raises:
        ValueError: the file is not an extended model; UntrustedCodeError (a
            ValueError) naming the file and the flag when the base needs consent.
    """
    base, declared, added = read_extended(path)
    check_base_consent(base, path, trust_code, available())
    return build_extended(load(base, trust_code=trust_code), declared, added)
