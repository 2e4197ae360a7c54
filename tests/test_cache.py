"""The persistent compilation cache is on by default, switchable, and private."""

import os
import stat
import subprocess
import sys

import pytest

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


KEPT = """
import os, sys, warnings, json
import jax, numpy as np, pandas as pd
import jaxcal
from jaxcal.calibrators.programs import on_disk

if sys.argv[1] == "again":  # a program kept on disk must not be traced again
    def refuse(*args, **kwargs):
        print("traced and exported again", file=sys.stderr)
        os._exit(7)
    on_disk.export.export = refuse
model = jaxcal.models.load("heat_exchanger")
rng = np.random.default_rng(0)
low, high = (np.asarray(b) for b in model.condition_range)
w = rng.uniform(low, high, (60, len(low)))
x = np.asarray(jax.vmap(lambda a: model.evaluate(a, model.nominal)[0])(w))
frame = pd.DataFrame(np.hstack([w, x * (1 + 0.01 * rng.standard_normal(x.shape))]),
                     columns=model.condition_names + model.output_names)
frame.insert(0, "unit", np.repeat([1, 2], 30))
noise = dict(zip(model.output_names, 0.01 * np.abs(x).mean(0)))
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    result = jaxcal.calibrate(model, frame, "ukf", noise=noise, progress=False)
print(json.dumps(np.asarray(result.theta).tolist()))
"""


def test_a_built_in_models_program_is_kept_on_disk_and_not_traced_again(tmp_path):
    env = {"JAXCAL_CACHE_DIR": str(tmp_path / "xla")}
    first = _run({**env}, KEPT.replace("sys.argv[1]", "'first'"))
    kept = list((tmp_path / "xla" / "jaxcal-programs").glob("*.jaxexport"))
    assert kept, "no program was kept"
    again = _run({**env}, KEPT.replace("sys.argv[1]", "'again'"))
    assert again == first  # the same numbers from the program read back
    off = _run({**env, "JAXCAL_CACHE": "0"}, KEPT.replace("sys.argv[1]", "'first'"))
    assert off == first  # the cache off: traced as before, same numbers


def test_only_the_most_recently_used_programs_are_kept(tmp_path):
    from jaxcal.calibrators.programs import on_disk

    for i in range(5):
        f = tmp_path / f"p{i}{on_disk.SUFFIX}"
        f.write_bytes(b"x")
        os.utime(f, (1000 + i, 1000 + i))
    (tmp_path / "other.bin").write_bytes(b"y")  # not a program: never touched
    on_disk._prune(tmp_path, keep=2)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["other.bin", f"p3{on_disk.SUFFIX}", f"p4{on_disk.SUFFIX}"]
    on_disk._prune(tmp_path, max_bytes=1)  # and their bytes: the newest alone fits
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "other.bin",
        f"p4{on_disk.SUFFIX}",
    ]


USER = """
import os, sys, warnings, json
import jax, jax.numpy as jnp, numpy as np, pandas as pd
import jaxcal
from jaxcal.calibrators.programs import on_disk

mode, offset = sys.argv[1], float(sys.argv[2])
if mode == "again":  # a program kept on disk must not be traced again
    def refuse(*args, **kwargs):
        print("traced and exported again", file=sys.stderr)
        os._exit(7)
    on_disk.export.export = refuse
def tank(w, theta):
    return jnp.stack([w[1] / theta[0], offset + w[0] / (w[1] * (1 + theta[1]))])
model = jaxcal.Model.from_function(
    tank, conditions=["heat", "inflow"], parameters={"leak": (1.0, 0.5, 2.0),
    "loss": (0.1, 0.0, 0.5)}, outputs=["level", "temp"])
rng = np.random.default_rng(0)
w = rng.uniform([5.0, 0.5], [30.0, 2.0], (60, 2))
x = np.asarray(jax.vmap(tank)(w, jnp.tile(jnp.array([1.2, 0.2]), (60, 1))))
frame = pd.DataFrame(np.hstack([w, x + 0.02 * rng.standard_normal(x.shape)]),
                     columns=["heat", "inflow", "level", "temp"])
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    result = jaxcal.calibrate(model, frame, "ukf", noise={"level": 0.02, "temp": 0.02},
                              progress=False)
print(json.dumps(np.asarray(result.theta).tolist()))
"""


def test_a_user_models_program_is_kept_by_what_it_computes(tmp_path):
    env = {"JAXCAL_CACHE_DIR": str(tmp_path / "xla")}

    def run(mode, offset):
        probe = USER.replace("sys.argv[1], float(sys.argv[2])", f"{mode!r}, {offset}")
        return _run(env, probe)

    first = run("first", 20.0)
    assert list((tmp_path / "xla" / "jaxcal-programs").glob("*.jaxexport"))
    assert run("again", 20.0) == first  # a new process reads it back, same numbers
    # the same function with another constant is another program: traced again
    # (the refused export ends the process), never the kept one's numbers
    env_all = {k: v for k, v in os.environ.items() if not k.startswith("JAXCAL_CACHE")}
    probe = USER.replace("sys.argv[1], float(sys.argv[2])", "'again', 21.0")
    out = subprocess.run(
        [sys.executable, "-c", probe], env={**env_all, **env, "JAX_PLATFORMS": "cpu"},
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 7, out.stderr


def test_a_kept_program_returns_the_heap_its_load_freed_once(tmp_path, monkeypatch):
    import jax
    import jax.numpy as jnp

    from jaxcal import cache
    from jaxcal.calibrators.programs import on_disk

    cache.return_freed_heap()  # glibc's malloc_trim here; a no-op elsewhere
    monkeypatch.setattr(cache, "is_enabled", lambda: True)
    monkeypatch.setattr(cache, "program_directory", lambda: str(tmp_path))
    trims = []
    monkeypatch.setattr(cache, "return_freed_heap", lambda: trims.append(1))
    run = on_disk.kept(jax.jit(lambda x: 2.0 * x), ("test", "double"))
    assert float(run(jnp.ones(3))[0]) == 2.0
    run(jnp.ones(3))
    assert len(trims) == 1  # the first call of a signature only
    run(jnp.ones(4))
    assert len(trims) == 2


_FREED = """
import gc, sys
import numpy as np
from jaxcal.cache import map_large_arrays
def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) * 1024
if sys.argv[1] == "fixed":
    assert map_large_arrays(1 << 20)
big = np.ones(30 << 17)  # 30 MB, mapped and freed: glibc's threshold rises to it
del big
arrays = [np.ones(4 << 17) for _ in range(40)]  # 4 MB each
before = rss()
del arrays[::2]  # holes in the heap, under its top
gc.collect()
print((before - rss()) / 1e6)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_large_arrays_mapped_apart_are_given_back_as_they_are_freed():
    """After a large block is freed glibc serves blocks of a few MB from the heap,
    which keeps the holes they leave; with a fixed threshold each is a mapping of
    its own, given back at once (the diagnosis's command line sets it)."""
    from jaxcal import cache

    freed = {}
    for mode in ("moving", "fixed"):
        out = subprocess.run([sys.executable, "-c", _FREED, mode], capture_output=True,
                             text=True, timeout=120)  # fmt: skip
        assert out.returncode == 0, out.stderr
        freed[mode] = float(out.stdout.split()[-1])
    assert freed["fixed"] > 70 and freed["moving"] < 20, freed  # 20 arrays, 84 MB
    with pytest.raises(ValueError, match="threshold"):
        cache.map_large_arrays(0)


def test_a_cluster_process_beyond_the_first_keeps_its_own_executable(
    tmp_path, monkeypatch
):
    """JAX writes its persistent cache from process 0 only: process 1 keeps the
    compiled executable itself and reads it back in its next run, uncompiled."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxcal.calibrators.programs import on_disk

    where = tmp_path / "xla"
    where.mkdir(mode=0o700)
    programs = where / "jaxcal-programs"
    monkeypatch.setattr(on_disk.cache, "is_enabled", lambda: True)
    monkeypatch.setattr(on_disk.cache, "program_directory", lambda: str(programs))
    monkeypatch.setattr(on_disk.jax, "process_index", lambda: 1)
    monkeypatch.setattr(on_disk.jax, "process_count", lambda: 2)
    fn = jax.jit(lambda a, b: (jnp.sin(a) * b, a.sum()))
    a, b = np.linspace(0.0, 1.0, 7), np.float64(3.0) * np.ones(7)
    first = on_disk.kept(fn, ("cluster-test",))(a, b)
    executables = list(programs.glob("*" + on_disk.EXECUTABLE_SUFFIX))
    assert len(executables) == 1 and "-p1of2d" in executables[0].name

    def refuse(self, *args, **kwargs):
        raise AssertionError("compiled again")

    monkeypatch.setattr(jax.stages.Lowered, "compile", refuse)
    again = on_disk.kept(fn, ("cluster-test",))(a, b)  # a new process's wrapper
    for x, y in zip(first, again, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(np.asarray(again[0]), np.sin(a) * b)
