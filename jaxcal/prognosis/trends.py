"""The trend families of a health parameter in age: ``polyN`` and ``expL``.

A family is a basis ``phi(s)`` at scaled ages ``s``; a unit's trend is ``phi(s) .
beta``, linear in its coefficients so that the degradation model's posterior stays
closed form (:mod:`jaxcal.prognosis.degradation`). ``polyN``: the powers ``(1, s, ...,
s^N)``; ``expL``: ``(1, s, exp(L s) - 1)``, the accelerating wear of damage-propagation
models (Saxena et al., PHM 2008) with a linear part.
"""

from __future__ import annotations

import jax.numpy as jnp


def _parse(trend: str) -> tuple[str, float]:
    """``("poly", N)`` or ``("exp", L)`` of a trend name (:func:`basis`)."""
    kind = next((k for k in ("poly", "exp") if str(trend).startswith(k)), "")
    try:
        number = float(str(trend)[len(kind) :]) if kind else float("nan")
    except ValueError:
        number = float("nan")
    if not number > 0:
        raise ValueError(
            f"trend {trend!r}: expected polyN (a polynomial of degree N >= 1) or expL "
            "(1, age and exp(L age) - 1, L > 0), e.g. poly2, exp2"
        )
    return kind, number


def check_trend(trend: str) -> str:
    """``trend`` if it names a trend family (:func:`basis`), else ``ValueError``."""
    kind, number = _parse(trend)
    if kind == "poly" and number != int(number):
        raise ValueError(f"trend {trend!r}: a polynomial's degree is a whole number")
    return trend


def size(trend: str) -> int:
    """The number of basis functions (coefficients) of ``trend``."""
    kind, number = _parse(trend)
    return int(number) + 1 if kind == "poly" else 3


def describe(trend: str) -> str:
    kind, number = _parse(trend)
    if kind == "poly":
        return f"a polynomial of degree {int(number)}"
    return f"a + b age + c (exp({number:g} age) - 1): wear that accelerates"


def basis(s, trend: str):
    """``[..., D]`` the trend's basis at scaled ages ``s``: ``polyN`` the powers
    ``(1, s, ..., s^N)``; ``expL`` ``(1, s, exp(L s) - 1)``, the exponential wear of
    damage-propagation models (Saxena et al., PHM 2008) with a linear part."""
    kind, number = _parse(trend)
    if kind == "poly":
        return s[..., None] ** jnp.arange(int(number) + 1)
    return jnp.stack([jnp.ones_like(s), s, jnp.expm1(number * s)], axis=-1)
