"""The persistent compilation cache is on by default, switchable, and private."""

import os
import stat
import subprocess
import sys

PROBE = """
import jax, jaxcal
from jaxcal import cache
assert not jax.config.jax_compilation_cache_dir  # importing jaxcal changes nothing
cache.ensure_default()
print(jax.config.jax_compilation_cache_dir or "OFF")
"""


def _run(env_extra, probe=PROBE):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAXCAL_CACHE")}
    env.update(env_extra, JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_on_by_default_in_a_private_directory(tmp_path):
    where = tmp_path / "xla"
    assert _run({"JAXCAL_CACHE_DIR": str(where)}) == str(where)
    assert stat.S_IMODE(where.stat().st_mode) == 0o700


def test_one_switch_turns_it_off(tmp_path):
    where = tmp_path / "xla"
    assert _run({"JAXCAL_CACHE_DIR": str(where), "JAXCAL_CACHE": "0"}) == "OFF"
    assert not where.exists()
    disabled = PROBE.replace(
        "cache.ensure_default()", "cache.disable()\ncache.ensure_default()"
    )
    assert _run({"JAXCAL_CACHE_DIR": str(where)}, disabled) == "OFF"


def test_a_program_that_chose_its_own_directory_keeps_it(tmp_path):
    chosen = PROBE.replace(
        "cache.ensure_default()",
        f"jax.config.update('jax_compilation_cache_dir', {str(tmp_path)!r})\n"
        "cache.ensure_default()",
    )
    assert _run({"JAXCAL_CACHE_DIR": str(tmp_path / "other")}, chosen) == str(tmp_path)
