"""The method registry: every method of :func:`jaxcal.calibrate`, registered once.

A method is one package ``jaxcal/calibrators/methods/<name>/`` exporting ``METHOD``,
a :class:`~jaxcal.calibrators.methods.protocol.Method` (its name, config, builders,
checks, noise policy and what it needs); :data:`PACKAGES` lists them and
:data:`REGISTRY` maps each name to its object. The front door, the fleet command
line and the paper's comparison read this registry and never test a method's name
or config type: adding a method is one package and one entry in :data:`PACKAGES`.

:func:`config` turns keyword options into a method's config (a misspelt option lists
the valid ones), :func:`build` makes it a ready
:class:`~jaxcal.calibrators.methods.options.Built` for a problem and :func:`make` one
stream's ``Calibrator(init, step)``.

Every method is run by a jitted fleet runner with a sample check (non-finite samples
and samples outside the valid input box are skipped and flagged). A row with some
outputs missing is used by a method whose calibrator accepts partial rows (the
filters, least squares) on its observed outputs and skipped by the others (reason
``x_partial``; :mod:`jaxcal.calibrators.guard`).
"""

from __future__ import annotations

import importlib

from jaxcal.calibrators.methods.options import Built, config_of, options_of
from jaxcal.calibrators.methods.protocol import Method
from jaxcal.data.buckets import Buckets
from jaxcal.problem import Problem

PACKAGES = ("ukf", "ls", "e2e", "policy", "ekf")  # the registry: one entry a method

REGISTRY: dict[str, Method] = {
    m.name: m
    for m in (importlib.import_module(f"{__name__}.{p}").METHOD for p in PACKAGES)
}
METHODS: dict[str, type] = {name: m.config for name, m in REGISTRY.items()}

__all__ = [
    "METHODS",
    "PACKAGES",
    "REGISTRY",
    "Built",
    "Method",
    "build",
    "config",
    "get",
    "make",
    "method_of",
    "options_of",
]


def get(name: str) -> Method:
    """The registered method ``name``.

    Raises:
        ValueError: an unknown name, listing the registered ones.
    """
    if name not in REGISTRY:
        raise ValueError(f"method must be one of {tuple(REGISTRY)}, got {name!r}")
    return REGISTRY[name]


def method_of(cfg) -> Method:
    """The registered method whose config ``cfg`` is."""
    for method in REGISTRY.values():
        if type(cfg) is method.config:
            return method
    raise ValueError(f"{type(cfg).__name__} is not a registered method's config")


def config(method: str, options: dict):
    """The config of ``method`` from keyword ``options`` (every one consumed).

    Raises:
        ValueError: an unknown method, an option the method does not take
            (listing the valid ones and the closest match), or an option of
            another type or range than it takes.
    """
    return config_of(method, get(method).config, options)


def build(problem: Problem, cfg, buckets: Buckets, seed: int = 0) -> Built:
    """:class:`Built` of the config ``cfg`` (:func:`config`) on ``problem``; ``buckets``
    are the data (E2E-sim trains on their conditions and float dtype)."""
    return method_of(cfg).build(problem, cfg, buckets, seed)


def make(problem: Problem, cfg, buckets: Buckets | None = None, seed: int = 0):
    """The method as one ``Calibrator(init, step)`` on ``problem`` (a stream's
    calibrator: a method on the model with the problem's noise and prior as
    constants, in the float dtype JAX defaults to)."""
    return method_of(cfg).make(problem, cfg, buckets, seed)
