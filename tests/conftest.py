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

# Clear JAX's caches after a module only past this many memory mappings: under a third
# of the kernel's limit (the next module has the rest), and high enough that most
# modules keep the programs the ones before them compiled (the turbofan's evaluation
# and linearisation of the session fixtures: a clear after every module made each
# next module trace and compile them again).
MAX_MAPPINGS = 20_000
# ... or past this resident memory: a loaded turbofan program keeps ~0.4 GB of host
# state (results/loop/profile.md), and two workers share the machine's memory.
MAX_RSS_KB = 4_000_000


def _num_mappings() -> int:
    """This process's memory mappings (0 where /proc is not there)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


def _rss_kb() -> int:
    """This process's resident memory in kB (0 where /proc is not there)."""
    try:
        with open("/proc/self/status") as status:
            line = next(x for x in status if x.startswith("VmRSS:"))
        return int(line.split()[1])
    except (OSError, StopIteration, ValueError):
        return 0


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop the compiled programs when a module ends with many mappings or much
    resident memory.

    Every loaded XLA:CPU executable holds its own memory mappings; one pytest process
    running the whole suite otherwise accumulates them past the kernel's limit
    (``vm.max_map_count``, 65,530 by default: measured ~55,000 mappings before the
    paper's quick run) and the next load crashes the process.
    """
    yield
    if _num_mappings() > MAX_MAPPINGS or _rss_kb() > MAX_RSS_KB:
        jax.clear_caches()
        gc.collect()


# The longest test files (setup + call: seconds on 2 quiet cores with a
# warm compilation cache). Under pytest-xdist they are handed out first: left to their
# place in the collection, the 2-minute quick paper run would start near the end and
# keep one worker busy alone for minutes. With a cold cache the order also decides who
# compiles a shared program: diagnosis/test_identify.py and test_diagnose.py compile the
# same turbofan linearisation, so they are kept apart (run at once, both workers compile
# it; measured: 1,010 s of the workers' time against 479 s one after the other).
LONGEST_FIRST = (
    "test_paper_quick.py",  # 131: experiments/paper.py preset=quick
    "diagnosis/test_identify.py",  # 18 warm; cold it compiles the linearisation
    "models/turbofan/physics/test_engine.py",  # 67
    "test_readme.py",  # 8: each README block with ukf, ls and e2e
    "paper/test_stream_form.py",  # 69
    "models/turbofan/physics/test_engine_hinted.py",  # 50
    "calibrators_peers/test_guard.py",  # 5
    "test_diagnose.py",  # 29
    "training/test_train_any_model.py",  # 63
    "fleet/test_distributed.py",  # 14
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
