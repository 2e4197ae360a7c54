"""The trust model (docs/trust.md): what jaxcal runs without the user's consent.

One test per rule: the on-disk caches are the user's own (created 0700; a folder
others can write is bypassed with one warning, and the answer stays right); a run
folder or a JSON spec never makes jaxcal import from the working directory or
``sys.path``, call an arbitrary callable, or run a ``.py`` without
``trust_code=True``; the NPE posterior loads with ``torch.load(weights_only=True)``.
"""

import os
import stat
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from jax import export

import jaxcal
from jaxcal import cache
from jaxcal.calibrators import on_disk


@pytest.fixture
def own_cache(tmp_path):
    """The process's cache switched to a fresh private folder for one test (jax's
    setting and jaxcal's switch restored after it)."""
    before = jax.config.jax_compilation_cache_dir, dict(cache._state)
    folder = tmp_path / "xla"
    folder.mkdir(mode=0o700)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    cache._state["disabled"] = False
    yield folder
    jax.config.update("jax_compilation_cache_dir", before[0])
    cache._state.update(before[1])


def _probe_cache(env_extra):
    """(stdout, stderr) of a fresh process turning the default cache on."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAXCAL_CACHE")}
    env.update(env_extra, JAX_PLATFORMS="cpu")
    probe = (
        "import jax\nfrom jaxcal import cache\ncache.ensure_default()\n"
        "cache.ensure_default()\n"  # a second call: still one warning
        "print(jax.config.jax_compilation_cache_dir or 'OFF')"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip(), out.stderr


def test_the_cache_folder_is_created_private(tmp_path):
    where = tmp_path / "new" / "xla"
    assert _probe_cache({"JAXCAL_CACHE_DIR": str(where)})[0] == str(where)
    assert stat.S_IMODE(where.stat().st_mode) == 0o700


def test_a_world_writable_cache_folder_is_bypassed_with_one_warning(tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    out, err = _probe_cache({"JAXCAL_CACHE_DIR": str(shared)})
    assert out == "OFF"  # run without the on-disk cache
    assert err.count("is not used") == 1, err
    assert str(shared) in err and "writable by other users" in err


@pytest.mark.skipif(os.getuid() != 0, reason="needs root to give a folder away")
def test_a_cache_folder_owned_by_another_user_is_bypassed(tmp_path):
    theirs = tmp_path / "theirs"
    theirs.mkdir(mode=0o700)
    os.chown(theirs, 65534, 65534)
    out, err = _probe_cache({"JAXCAL_CACHE_DIR": str(theirs)})
    assert out == "OFF" and "owned by user id 65534" in err, err


def test_a_planted_program_runs_only_from_a_private_folder(own_cache):
    fn = jax.jit(lambda x: 2.0 * x)
    key = ("tests/test_trust.py", "planted")
    x = jnp.arange(3.0)
    np.testing.assert_allclose(on_disk.kept(fn, key)(x), 2.0 * x)
    [program] = (own_cache / "jaxcal-programs").glob("*" + on_disk.SUFFIX)
    # another program of the same signature written over it: adds 0.25
    planted = export.export(jax.jit(lambda x: 2.0 * x + 0.25))(x).serialize()
    program.write_bytes(bytes(planted))
    # in a private folder the file is the user's own and is run (the attack's means)
    np.testing.assert_allclose(on_disk.kept(fn, key)(x), 2.0 * x + 0.25)
    program.parent.chmod(0o777)  # now anyone could have written it: not run
    with pytest.warns(UserWarning, match="is not used, it is writable by other"):
        out = on_disk.kept(fn, key)(x)
    np.testing.assert_allclose(out, 2.0 * x)


def test_a_world_writable_program_file_is_not_run(own_cache):
    fn = jax.jit(lambda x: 3.0 * x)
    key = ("tests/test_trust.py", "file mode")
    x = jnp.arange(2.0)
    on_disk.kept(fn, key)(x)
    [program] = (own_cache / "jaxcal-programs").glob("*" + on_disk.SUFFIX)
    planted = export.export(jax.jit(lambda x: 3.0 * x + 0.25))(x).serialize()
    program.write_bytes(bytes(planted))
    program.chmod(0o666)
    with pytest.warns(UserWarning, match="writable by other users"):
        out = on_disk.kept(fn, key)(x)
    np.testing.assert_allclose(out, 3.0 * x)


def _tank_frame():
    def tank(w, theta):
        return jnp.stack([w[1] / theta[0], 20.0 + w[0] / (w[1] * (1 + theta[1]))])

    model = jaxcal.Model.from_function(
        tank, conditions=["heat", "inflow"], outputs=["level", "temp"],
        parameters={"leak": (1.0, 0.5, 2.0), "loss": (0.1, 0.0, 0.5)},
    )  # fmt: skip
    rng = np.random.default_rng(0)
    w = rng.uniform([5.0, 0.5], [30.0, 2.0], (40, 2))
    x = np.asarray(jax.vmap(tank)(w, jnp.tile(jnp.array([1.2, 0.2]), (40, 1))))
    frame = pd.DataFrame(
        np.hstack([w, x + 0.02 * rng.standard_normal(x.shape)]),
        columns=["heat", "inflow", "level", "temp"],
    )
    return model, frame


@pytest.mark.filterwarnings("error::DeprecationWarning")
def test_a_clean_calibrate_raises_no_deprecation_warning(own_cache):
    model, frame = _tank_frame()
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        result = jaxcal.calibrate(
            model, frame, "ukf", noise={"level": 0.02, "temp": 0.02}, progress=False
        )
    assert np.isfinite(np.asarray(result.theta)).all()
    # the program went through the on-disk path (where the warning was raised)
    assert list((own_cache / "jaxcal-programs").glob("*" + on_disk.SUFFIX))
