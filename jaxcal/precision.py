"""Floating-point precision policy.

The engine's Newton solve and its implicit gradients need float64 (conservation closes
to 1e-8 and finite-difference checks reach 1e-5 only in double precision); networks
stay float32. Float64 is therefore switched on by entry points (CLIs, tests,
experiments) with :func:`enable_x64`, never at import time, as the style guide asks.
Library code that needs it asks :func:`is_x64` (the one check; it follows ``with
jax.enable_x64(...)`` scopes too) or stops with :func:`require_x64`'s one message.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def enable_x64() -> None:
    """Switch JAX to 64-bit floats for the rest of the process (entry points only)."""
    jax.config.update("jax_enable_x64", True)


def is_x64() -> bool:
    """True when JAX creates float64 arrays by default."""
    return bool(jax.config.jax_enable_x64)


def require_x64(what: str) -> None:
    """Raise a clear error when float64 is off.

    Args:
        what: who needs float64 and why, the start of the message (``"model 'cmapss'
            needs float64 (an iterative solver inside)"``).

    Raises:
        ValueError: x64 is disabled.
    """
    if not is_x64():
        raise ValueError(
            f"{what}: call jax.config.update('jax_enable_x64', True) (or "
            "jaxcal.precision.enable_x64()) at the start of the program"
        )


def float_dtype():
    """The widest float dtype JAX currently allows (float64 under x64, else float32)."""
    return jnp.zeros((), dtype=float).dtype
