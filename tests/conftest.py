"""Shared test set-up: CPU only, float64 on (the engine solver needs it)."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

from jaxcal.precision import enable_x64  # noqa: E402

enable_x64()
