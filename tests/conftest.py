"""Shared test set-up: CPU only, float64 on (the engine solver needs it), and the
persistent XLA compilation cache (the engine takes tens of seconds to compile).

``make test`` runs the suite on two pytest-xdist workers, one test file per worker at
a time (``--dist loadfile``: the many module-scoped fixtures are built once).
"""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

from jaxcal.cache import enable_compilation_cache  # noqa: E402
from jaxcal.precision import enable_x64  # noqa: E402

enable_x64()
enable_compilation_cache()

import gc  # noqa: E402
from pathlib import Path  # noqa: E402

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


# The longest test files (warm compilation cache, one worker; the numbers are seconds
# measured on 2 cores), longest first. Under pytest-xdist they are handed out first:
# left to their place in the collection, the 2-3 minute quick paper run would start
# near the end and keep one worker busy alone for minutes.
LONGEST_FIRST = (
    "test_paper_quick.py",  # 190: experiments/paper.py preset=quick
    "diagnosis/test_identify.py",  # 160
    "physics/test_engine.py",  # 96
    "test_readme.py",  # 73: each README block with ukf, ls and e2e
    "paper/test_stream_form.py",  # 68
    "physics/test_engine_hinted.py",  # 67
    "calibrators_peers/test_guard.py",  # 48
    "test_diagnose.py",  # 48
    "training/test_train_any_model.py",  # 33
    "fleet/test_distributed.py",  # 31
)


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist, move the files of ``LONGEST_FIRST`` to the front (a stable
    sort: every file keeps its own order; a plain run keeps the collection order).
    Used with ``--no-loadscope-reorder``, which would order files by test count."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    here = Path(__file__).parent
    rank = {str(here / name): i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(str(item.path), len(rank)))
