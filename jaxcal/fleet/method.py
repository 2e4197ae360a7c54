"""The calibrator of a fleet run, from the method table of the front door.

The fleet builds its method as :func:`jaxcal.calibrate` does
(:mod:`jaxcal.calibrators.methods`): the command line's options become the method's
frozen config (:func:`method_options`, then ``methods.config``), the data's sample a
:class:`~jaxcal.problem.Problem` (:func:`build_problem`), and the two one
``Calibrator(init, step)`` with its sample check (:func:`make_method`): the model's
valid inputs for the UKF and least squares, the run's training range for a policy,
the data's range for E2E.

The measurement noise is ``noise=`` (one std per output, or one for all). Without it
the fleet does not estimate one (the front door's screening passes need the whole
data set): for the turbofan it keeps its known default, 1 % of each output's spread
over the selected rows (the paper's ``r = 0.01`` in normalised units, what the fleet
always used); another model needs ``noise=`` for the UKF, least squares and E2E.
A policy reads no noise.
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators import methods
from jaxcal.calibrators.interface import Calibrator, SampleCheck
from jaxcal.data.buckets import bucket_units
from jaxcal.model import Model
from jaxcal.problem import Problem
from jaxcal.settings import coerce

METHOD_ALIASES = {"least_squares": "ls"}  # the fleet's old method name
# ``<prefix>.<option>=value`` of the old nested configs -> the flat option
OPTION_PREFIXES = {"ukf": "ukf", "least_squares": "ls", "ls": "ls"}
NOT_ON_COMMAND_LINE = ("e2e", "e2e_config")  # Python objects: jaxcal.calibrate


class FleetMethod(NamedTuple):
    """A fleet run's method: its problem, calibrator and sample check."""

    problem: Problem
    calibrator: Calibrator
    check: SampleCheck | None


def canonical(method: str) -> str:
    """The method table's name of a fleet method name (``least_squares`` -> ``ls``)."""
    return METHOD_ALIASES.get(method, method)


def _option_type(config_type, name: str):
    inner = getattr(config_type, "field_type", None)
    if inner is not None and name in {f.name for f in dataclasses.fields(inner)}:
        return typing.get_type_hints(inner)[name]
    return typing.get_type_hints(config_type).get(name, Any)


def _state_value(text: str, key: str):
    """``state_std`` / ``state_q``: one number, ``a,b`` per state or
    ``name:value,...``."""
    parts = [p.strip() for p in text.split(",") if p.strip()]
    try:
        if parts and all(":" in p for p in parts):
            return {k.strip(): float(v) for k, v in (p.split(":", 1) for p in parts)}
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise ValueError(
            f"{key}={text!r}: expected a number, one per state (a,b) or state:value,..."
        ) from None
    if not values:
        raise ValueError(f"{key}: empty value")
    return values[0] if len(values) == 1 else values


def _unknown_keys(unknown, method: str, valid, fleet_keys) -> ValueError:
    said = []
    for key, name in unknown:
        hint = difflib.get_close_matches(name, [*valid, *fleet_keys], n=1)
        said.append(f"{key!r}" + (f" (did you mean {hint[0]!r}?)" if hint else ""))
        if name == "r":
            said[-1] += " (the measurement noise is noise=, per output or one number)"
    plural = "s" if len(unknown) > 1 else ""
    return ValueError(
        f"unknown key{plural} {', '.join(said)}: method={method!r} takes the options "
        f"{', '.join(sorted(valid))}; the fleet's own keys are "
        f"{', '.join(sorted(fleet_keys))}"
    )


def method_options(
    method: str, tokens: Sequence[tuple[str | None, str, str]], fleet_keys
) -> tuple[tuple[str, Any], ...]:
    """Typed options of ``method`` from command-line tokens.

    Args:
        method: a name of the method table (``ukf``, ``ls``, ``e2e``, ``policy``).
        tokens: ``(prefix, name, text)``: ``q=0.001`` is ``(None, "q", "0.001")``,
            the old ``ukf.q=0.001`` ``("ukf", "q", "0.001")`` (a prefix of another
            method is an error).
        fleet_keys: the command line's other keys (named in the error message).

    Returns:
        ``((name, value), ...)`` sorted by name, for ``methods.config``.

    Raises:
        ValueError: an option the method does not take (listing the valid ones and
            the closest match), a repeated one, or a badly typed value.
    """
    config_type = methods.get(method).config
    valid = methods.options_of(config_type)
    options: dict[str, Any] = {}
    unknown = []
    for prefix, name, text in tokens:
        key = f"{prefix}.{name}" if prefix else name
        if prefix is not None and OPTION_PREFIXES[prefix] != method:
            raise ValueError(
                f"{key}: a setting of method={OPTION_PREFIXES[prefix]!r}, but "
                f"method={method!r}"
            )
        if name not in valid:
            unknown.append((key, name))
            continue
        if name in options:
            raise ValueError(f"option {name!r} given twice")
        if name in NOT_ON_COMMAND_LINE:
            raise ValueError(
                f"{key}: a Python object, not a command-line value (jaxcal.calibrate "
                "takes it)"
            )
        if name.startswith("state_"):
            options[name] = _state_value(text, key)
        else:
            tp = _option_type(config_type, name)
            options[name] = coerce(text, str if tp is Any else tp, key)
    if unknown:
        raise _unknown_keys(unknown, method, valid, fleet_keys)
    return tuple(sorted(options.items()))


def parse_noise(text: str) -> dict[str, float] | float | None:
    """``noise=``: ``name:std,...`` per output, or one number for every output
    (``""``: not given)."""
    text = text.strip()
    if not text:
        return None
    try:
        if ":" not in text:
            value = float(text)
        else:
            pairs = [p.split(":", 1) for p in text.split(",") if p.strip()]
            value = {k.strip(): float(v) for k, v in pairs}
    except ValueError:
        raise ValueError(
            f"noise={text!r}: expected name:std,... per output or one number"
        ) from None
    values = list(value.values()) if isinstance(value, dict) else [value]
    if not all(np.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"noise={text!r}: every std must be finite and > 0")
    return value


def require_noise(model: Model, method: str, noise, default_noise=None) -> None:
    """A ValueError when ``method`` on ``model`` needs ``noise=`` and has none (nor
    a ``default_noise``, :func:`build_problem`)."""
    if noise is None and methods.get(method).reads_noise and default_noise is None:
        raise ValueError(
            f"model {model.name!r}: pass noise= (the measurement noise std, "
            "name:std,... per output or one number for all); the fleet has a "
            "default only for the turbofan (jaxcal.calibrate estimates it from the "
            "data)"
        )


def build_problem(
    model: Model,
    source,
    *,
    theta: Sequence[str],
    method: str,
    noise: dict[str, float] | float | None = None,
    default_noise: tuple[float, str] | None = None,
    theta0: Sequence[float] = (),
) -> Problem:
    """The :class:`Problem` of a :class:`~jaxcal.fleet.sources.FleetSource`.

    Args:
        model: the model. source: the data (its ``sample``, ``outputs`` and, for a
            streamed file, ``x_stats``: the outputs' mean and std over every
            selected row, which replace the sample's in the problem's
            normalisation).
        theta: declared parameters. method: the method table's name.
        noise: :func:`parse_noise`'s value (``None``: the module docstring).
        default_noise: ``(share, label)``, the model's noise without ``noise=``:
            ``share`` of each output's spread (the turbofan's,
            :data:`jaxcal.models.turbofan.model.FLEET_NOISE`; None: noise= is needed).
        theta0: prior mean per declared parameter (``()``: the nominal values).

    Raises:
        ValueError: names that do not match, a missing ``noise=``, a bad ``theta0``.
    """
    require_noise(model, method, noise, default_noise)
    outputs = source.outputs
    given = [noise] * len(outputs) if isinstance(noise, float) else noise
    problem = Problem.build(
        model, source.sample, theta=theta, outputs=outputs, noise=given
    )
    if source.x_stats is not None:  # a streamed file
        x_mean, x_std = source.x_stats  # the outputs' over every selected row
        norm = problem.norm._replace(
            x_mean=np.asarray(x_mean, np.float64), x_std=np.asarray(x_std, np.float64)
        )
        problem = dataclasses.replace(problem, norm=norm)
    if noise is None and default_noise is not None:
        share, label = default_noise
        problem = problem.with_noise(
            share * problem.norm.x_std, f"{label} ({source.norm_source})"
        )
    if theta0:
        if len(theta0) != len(problem.theta_names):
            raise ValueError(
                f"theta0 needs one value per theta name {list(problem.theta_names)}"
            )
        base = problem.theta_base.copy()
        base[problem.theta_index] = np.asarray(theta0, np.float64)
        problem = dataclasses.replace(problem, theta_base=base)
    return problem


def make_method(problem: Problem, cfg, source, seed: int = 0) -> FleetMethod:
    """The calibrator and sample check of the config ``cfg`` on ``problem``
    (module docstring); a policy's ``cfg.run`` is a loaded run."""
    method = methods.method_of(cfg)
    buckets = None
    if method.needs_all_rows:  # it learns from the whole data set first
        if not source.complete:
            raise ValueError(
                f"method={method.name} learns from the conditions of the whole data "
                "set: give the data as a table (.csv, .parquet), or use "
                "jaxcal.calibrate"
            )
        buckets = bucket_units(source.sample, jnp.zeros((), float).dtype)
    calibrator = method.make(problem, cfg, buckets, seed)
    return FleetMethod(problem, calibrator, method.check(problem, cfg))
