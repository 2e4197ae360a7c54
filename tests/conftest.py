"""Shared test set-up: CPU only, float64 on (the engine solver needs it), and the
persistent XLA compilation cache (the engine takes tens of seconds to compile)."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

from jaxcal.precision import enable_compilation_cache, enable_x64  # noqa: E402

enable_x64()
enable_compilation_cache()
