"""Floating-point precision policy.

The engine's Newton solve and its implicit gradients need float64 (conservation closes to
1e-8 and finite-difference checks reach 1e-5 only in double precision); networks stay
float32. Float64 is therefore switched on by entry points (CLIs, tests, experiments) with
:func:`enable_x64`, never at import time, as the style guide asks.
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


def float_dtype():
    """The widest float dtype JAX currently allows (float64 under x64, else float32)."""
    return jnp.zeros((), dtype=float).dtype
