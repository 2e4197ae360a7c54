"""Shared test set-up: CPU only, float64 on (the engine solver needs it), and the
persistent XLA compilation cache (the engine takes tens of seconds to compile)."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

from jaxcal.precision import enable_compilation_cache, enable_x64  # noqa: E402

enable_x64()
enable_compilation_cache()

import gc  # noqa: E402

import jax  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop each test module's compiled programs when it ends.

    Every loaded XLA:CPU executable holds its own memory mappings; one pytest process
    running the whole suite otherwise accumulates them past the kernel's limit
    (``vm.max_map_count``, 65,530 by default: measured ~55,000 mappings before the
    paper's quick run) and the next load crashes the process.
    """
    yield
    jax.clear_caches()
    gc.collect()
