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


def enable_compilation_cache(path: str | None = None) -> None:
    """Persist compiled XLA programs on disk (entry points and tests only).

    The engine's Newton solve takes 10-60 s to compile on a small CPU; the cache makes
    every later process that builds the same program start in seconds. The directory
    defaults to ``$JAXCAL_CACHE_DIR`` or ``~/.cache/jaxcal/xla``.
    """
    import os

    path = path or os.environ.get("JAXCAL_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "jaxcal", "xla"
    )
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
