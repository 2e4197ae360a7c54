"""A method's keyword options read into its config, every option's form checked.

Each method's config is a frozen, hashable dataclass of its package
(:mod:`jaxcal.calibrators.methods`); :func:`config_of` turns keyword options into
one (a misspelt option lists the valid ones and the closest match). A config is
hashable, so it keys the compiled programs
(:mod:`jaxcal.calibrators.programs.compiled`); what makes it a ready :class:`Built`
for a problem is its method's ``build`` (a learned method's: :func:`learned_built`).
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator, run_fleet
from jaxcal.data.padded import Padded
from jaxcal.problem import Problem


def _frozen(value):
    """A state option as a hashable value (a ``{state: value}`` as sorted pairs, an
    array as a tuple); what cannot be read is left for
    :func:`~jaxcal.calibrators.methods.on_model.state_option` to refuse with its
    message."""
    try:
        if isinstance(value, dict):
            return tuple(sorted((k, float(v)) for k, v in value.items()))
        if value is None or isinstance(value, (int, float, str)):
            return value
        return tuple(np.ravel(np.asarray(value, np.float64)).tolist())
    except (TypeError, ValueError):
        return value


# Each option's accepted form: (kind, what it is). Kinds: "positive", "real",
# "non-negative", "above-one" (finite numbers), "count" (an integer >= 1), "flag"
# (a bool), "state" (None, a number, [Z] numbers or {state: number}, finite >= 0);
# "-" options are read by their own loaders. A trailing "?" also accepts None.
_FORMS: dict[str, tuple[str, str]] = {
    "q": ("positive", "the parameters' random-walk std per step, in half-box units"),
    "prior_std": ("positive", "the prior std of theta, in half-box units"),
    "alpha": ("positive", "the sigma points' spread"),
    "beta": ("real", "the centre point's covariance weight"),
    "kappa": ("real", "the secondary spread"),
    "jitter": ("non-negative", "added to the covariance diagonal"),
    "posterior_xhat": ("flag", "report xhat at the posterior theta"),
    "return_cov": ("flag", "also report theta_cov"),
    "window": ("count", "samples in the sliding window"),
    "num_iters": ("count", "Levenberg-Marquardt iterations per sample"),
    "damping_init": ("positive", "the initial Marquardt damping"),
    "damping_factor": ("above-one", "the damping's factor"),
    "state_std": ("state", "the initial state's std"),
    "state_q": ("state", "the states' process noise per step"),
    "e2e_window": ("count?", "past samples the network reads"),
    "e2e_copies": ("count", "simulated fleets"),
}
_EXPECTED = {
    "positive": "a finite number > 0",
    "real": "a finite number",
    "non-negative": "a finite number >= 0",
    "above-one": "a finite number > 1",
    "count": "an integer >= 1",
    "flag": "True or False",
    "state": "a finite number >= 0, one per state ([Z]) or {state: number}",
}


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )


def _form_ok(kind: str, value) -> bool:
    """``value`` has the form ``kind`` of :data:`_FORMS`."""
    if kind == "flag":
        return isinstance(value, (bool, np.bool_))
    if kind == "count":
        return _is_number(value) and float(value).is_integer() and value >= 1
    if kind == "state":
        values = value.values() if isinstance(value, dict) else np.ravel(value)
        if isinstance(value, str) or (isinstance(value, dict) and not value):
            return False
        return all(_is_number(v) and np.isfinite(v) and v >= 0 for v in values)
    if not (_is_number(value) and np.isfinite(value)):
        return False
    return {
        "positive": value > 0, "real": True, "non-negative": value >= 0,
        "above-one": value > 1,
    }[kind]  # fmt: skip


def _plain(name: str, value):
    """A checked option as a plain Python value (``np.int64(8)`` -> ``8``: a numpy
    integer window would turn the ring buffer's int32 position into int64)."""
    kind = _FORMS.get(name, ("-", ""))[0].rstrip("?")
    if value is None or kind in ("-", "state"):
        return value
    return {"count": int, "flag": bool}.get(kind, float)(value)


def check_options(method: str, options: dict, config_type=None) -> None:
    """Every option of ``options`` has its expected form (:data:`_FORMS`): type,
    finiteness and range, checked before any config is built (``q="0.01"`` or a
    window of ``32.5`` would otherwise fail inside a comparison, ``q=inf`` run a
    filter that never settles).

    Raises:
        ValueError: naming the method, the option, what it is, its expected form
            and what was given.
    """
    for name, value in options.items():
        kind, what = _FORMS.get(name, ("-", ""))
        optional = kind.endswith("?") or name in getattr(config_type, "may_be_none", ())
        kind = kind.rstrip("?")
        if kind == "-" or (value is None and (optional or kind == "state")):
            continue
        if name == "e2e_config":
            continue
        if not _form_ok(kind, value):
            expected = _EXPECTED[kind] + (" or None" if optional else "")
            raise ValueError(
                f"method={method!r}: option {name}={value!r} is not {expected} "
                f"({name}: {what})"
            )
    config_ = options.get("e2e_config")
    if config_ is not None:
        # cycle: the e2e package imports this module
        from jaxcal.calibrators.methods.e2e.network import E2EConfig

        if not isinstance(config_, E2EConfig):
            raise ValueError(
                f"method={method!r}: option e2e_config must be an E2EConfig or None, "
                f"got a {type(config_).__name__}"
            )


class Built(NamedTuple):
    """A method ready to run: ``run(padded, skip=None) -> CalOutput`` per padded
    group (``skip [U, T]``: cells skipped like padding), and ``prior_std [P]``,
    what is known of theta before a stream's first sample."""

    run: Callable
    prior_std: np.ndarray
    calibrator: Calibrator | None = None  # E2E, a policy (the model-based: make())


_FLEET = jax.jit(run_fleet, static_argnums=0)  # one dispatch cache per process


def learned_built(problem: Problem, cal: Calibrator, check) -> Built:
    """:class:`Built` of a learned method's calibrator, made outside the compiled
    programs (an E2E network, a trained policy): the jitted fleet scan with the
    method's sample ``check`` (the same calibrator object again runs without tracing
    again), and a uniform's std over the box before a stream's first sample."""

    def run(padded: Padded, skip=None):
        mask = padded.mask if skip is None else padded.mask & ~np.asarray(skip)
        return _FLEET(
            cal, jnp.asarray(padded.w), jnp.asarray(padded.x),
            jnp.asarray(mask), check=check,
        )  # fmt: skip

    uniform = problem.theta_half_width / np.sqrt(3.0)
    return Built(run, uniform, cal)


def options_of(config_type) -> tuple[str, ...]:
    """The keyword options of a method's config."""
    names = [f.name for f in dataclasses.fields(config_type)]
    inner = getattr(config_type, "field_type", None)
    if inner is not None:
        names.remove(config_type.field_name)
        names += [f.name for f in dataclasses.fields(inner) if f.name != "r"]
    return tuple(names)


def config_of(method: str, config_type, options: dict):
    """The config (of type ``config_type``) of ``method`` from keyword ``options``
    (every one consumed).

    Raises:
        ValueError: an option the method does not take (listing the valid ones and
            the closest match), or an option of another type or range than it
            takes (:func:`check_options`).
    """
    valid = options_of(config_type)
    unknown = sorted(set(options) - set(valid))
    if unknown:
        hints = [difflib.get_close_matches(k, valid, n=1) for k in unknown]
        said = "; ".join(
            f"{k!r}" + (f" (did you mean {h[0]!r}?)" if h else "")
            for k, h in zip(unknown, hints, strict=True)
        )
        raise ValueError(
            f"unknown option(s) for method={method!r}: {said}; its options are "
            f"{sorted(valid)}"
        )
    check_options(method, options, config_type)
    options = {k: _plain(k, v) for k, v in options.items()}
    kwargs = {}
    inner = getattr(config_type, "field_type", None)
    if inner is not None:
        names = {f.name for f in dataclasses.fields(inner)} - {"r"}
        inner_kw = {k: options[k] for k in options if k in names}
        kwargs[config_type.field_name] = inner(r=1.0, **inner_kw)
    for f in dataclasses.fields(config_type):
        if f.name in options:
            value = options[f.name]
            kwargs[f.name] = _frozen(value) if f.name.startswith("state_") else value
    return config_type(**kwargs)
