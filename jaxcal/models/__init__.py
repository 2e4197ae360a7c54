"""The model registry: ``jaxcal.models.load(spec) -> Model``.

``spec`` is a registered name (``"cmapss"``, ``"agtf30"``: the turbofans;
``"heat_exchanger"``: a small static example), ``"package.module:attr"`` or
``"path/to/file.py:attr"``, where ``attr`` is a :class:`~jaxcal.model.Model` or a
callable returning one. The command lines take the same spec as ``model=``.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from collections.abc import Callable

from jaxcal.model import Model

_REGISTRY: dict[str, Callable[[], Model]] = {}


def register(name: str, factory: Callable[[], Model]) -> None:
    """Make ``load(name)`` return ``factory()`` (a zero-argument callable)."""
    _REGISTRY[name] = factory


def available() -> tuple[str, ...]:
    """The registered model names."""
    return tuple(sorted(_REGISTRY))


def _from_attr(obj, spec: str) -> Model:
    if isinstance(obj, Model):
        return obj
    if callable(obj):
        model = obj()
        if isinstance(model, Model):
            return model
    raise ValueError(
        f"model={spec!r}: the attribute is neither a jaxcal.Model nor a callable "
        "returning one"
    )


def _load_file(path: str, spec: str):
    if not os.path.isfile(path):
        raise ValueError(f"model={spec!r}: file {path} not found")
    name = "_jaxcal_user_model_" + os.path.splitext(os.path.basename(path))[0]
    module_spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module  # dataclasses and pickling look the module up
    module_spec.loader.exec_module(module)
    return module


def load(spec: str | Model) -> Model:
    """The model named by ``spec`` (see the module docstring).

    Raises:
        ValueError: an unknown name, a missing file or attribute, or an attribute
            that is not a model; the message lists the registered names.
    """
    if isinstance(spec, Model):
        return spec
    spec = str(spec)
    if spec in _REGISTRY:
        return _REGISTRY[spec]()
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
    if not hasattr(module, attr):
        raise ValueError(f"model={spec!r}: {where} has no attribute {attr!r}")
    return _from_attr(getattr(module, attr), spec)


def _turbofan(name: str) -> Callable[[], Model]:
    def factory() -> Model:
        from jaxcal.models.turbofan import load_turbofan

        return load_turbofan(name)

    return factory


def _heat_exchanger() -> Model:
    from jaxcal.models.heat_exchanger import heat_exchanger_model

    return heat_exchanger_model()


register("cmapss", _turbofan("cmapss"))
register("agtf30", _turbofan("agtf30"))
register("heat_exchanger", _heat_exchanger)

__all__ = ["available", "load", "register"]
