"""The trust model (docs/trust.md): what jaxcal runs without the user's consent.

One test per rule: the on-disk caches are the user's own (created 0700; a folder
others can write is bypassed with one warning, and the answer stays right); a run
folder or a JSON spec never makes jaxcal import from the working directory or
``sys.path``, call an arbitrary callable, or run a ``.py`` without
``trust_code=True``; the NPE posterior loads with ``torch.load(weights_only=True)``.
"""

import json
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
from jaxcal.calibrators.programs import on_disk


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


def test_a_cache_folder_owned_by_another_user_is_refused(tmp_path, monkeypatch):
    """Giving a folder away needs root; seen from another user id, a folder of
    ours is theirs: the same check (the bypass itself: the test above)."""
    from jaxcal import cache

    theirs = tmp_path / "theirs"
    theirs.mkdir(mode=0o700)
    owner = theirs.stat().st_uid
    assert cache.private_problem(theirs) is None
    monkeypatch.setattr(cache.os, "getuid", lambda: owner + 1)
    problem = cache.private_problem(theirs)
    assert problem == f"it is owned by user id {owner}, not by this user ({owner + 1})"


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


# ------------------------------------------------------------------ code: runs, specs

MODEL_SOURCE = """
import jax.numpy as jnp
import jaxcal

open({marker!r}, "a").write("ran\\n")  # what a planted file would do

def toy(w, theta):
    return jnp.stack([theta[0] * w[0], theta[1] + w[1]])

MODEL = jaxcal.Model.from_function(
    toy, conditions=("a", "b"), outputs=("y1", "y2"), name="toy",
    parameters={{"p": (1.0, 0.5, 2.0), "q": (0.5, 0.1, 1.0)}},
)
"""


def _run_folder(tmp_path, source: dict, copy: str | None = None):
    """A run folder whose data.json names ``source`` (and a model copy ``copy``):
    enough for the loaders to reach the model, which they must refuse first."""
    from jaxcal.runs.checkpoint import save_config
    from jaxcal.training.config import TrainConfig

    run = tmp_path / "received_run"
    (run / "model").mkdir(parents=True)
    save_config(run, TrainConfig())
    if copy is not None:
        (run / "model" / "toy_model.py").write_text(copy)
    (run / "data.json").write_text(json.dumps({"model_source": source, "x64": False}))
    return run


def _file_record(content: str) -> dict:
    import hashlib

    return {
        "kind": "file", "file": "model/toy_model.py", "attr": "MODEL",
        "sha256": hashlib.sha256(content.encode()).hexdigest(), "origin": "elsewhere",
    }  # fmt: skip


def test_a_runs_model_copy_runs_only_with_consent(tmp_path):
    from jaxcal.deploy import StreamingCalibrator
    from jaxcal.training.model_source import load_run_model
    from jaxcal.trust import UntrustedCodeError

    marker = tmp_path / "ran"
    content = MODEL_SOURCE.format(marker=str(marker))
    run = _run_folder(tmp_path, _file_record(content), copy=content)
    copy = run / "model" / "toy_model.py"
    with pytest.raises(UntrustedCodeError) as err:
        StreamingCalibrator(run)
    message = str(err.value)
    assert str(copy) in message and "trust_code=True" in message
    assert "trust_code=true" in message  # the command lines' spelling
    assert not marker.exists()  # nothing of it ran
    data = json.loads((run / "data.json").read_text())
    model = load_run_model(run, data, trust_code=True)  # consent: it runs
    assert model.name == "toy" and marker.exists()


def test_a_file_the_user_named_is_consent_for_the_same_bytes(tmp_path):
    from jaxcal.training.model_source import load_run_model
    from jaxcal.trust import UntrustedCodeError

    marker = tmp_path / "ran"
    content = MODEL_SOURCE.format(marker=str(marker))
    mine = tmp_path / "mine.py"
    mine.write_text(content)
    run = _run_folder(tmp_path, _file_record(content), copy=content)
    data = json.loads((run / "data.json").read_text())
    jaxcal.models.load(f"{mine}:MODEL")  # the user names the file: consent
    assert load_run_model(run, data).name == "toy"
    # other bytes (one more line) were not named: refused
    other = content + "\n# another file\n"
    run2 = _run_folder(tmp_path / "2", _file_record(other), copy=other)
    with pytest.raises(UntrustedCodeError, match="trust_code"):
        load_run_model(run2, json.loads((run2 / "data.json").read_text()))


def test_a_runs_module_is_never_imported_from_the_working_directory(
    tmp_path, monkeypatch
):
    from jaxcal.deploy import StreamingCalibrator
    from jaxcal.trust import UntrustedCodeError

    marker = tmp_path / "ran"
    (tmp_path / "planted_model_h42.py").write_text(
        MODEL_SOURCE.format(marker=str(marker))
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))  # as `python -m` puts the cwd first
    source = {"kind": "module", "module": "planted_model_h42", "attr": "MODEL",
              "sha256": "0" * 64}  # fmt: skip
    run = _run_folder(tmp_path, source)
    with pytest.raises(UntrustedCodeError, match="planted_model_h42:MODEL.*trust_code"):
        StreamingCalibrator(run)
    assert not marker.exists() and "planted_model_h42" not in sys.modules


@pytest.mark.parametrize(
    "source, spec",
    [
        ({"kind": "module", "module": "os", "attr": "getpid", "sha256": "0"}, None),
        ({"kind": "registered", "name": "os:getpid"}, None),
        (None, "os:getpid"),  # the older layout: a bare model_spec
    ],
)
def test_a_run_never_calls_an_arbitrary_callable(tmp_path, monkeypatch, source, spec):
    from jaxcal.training.model_source import load_run_model

    calls = []
    monkeypatch.setattr(os, "getpid", lambda: calls.append(1) or 1)
    data = {"model_source": source} if source else {"model_spec": spec}
    with pytest.raises(ValueError, match="trust_code|not a model this jaxcal"):
        load_run_model(tmp_path, data)
    assert calls == []


def test_a_json_specs_python_base_runs_only_with_consent(tmp_path):
    from jaxcal.trust import UntrustedCodeError

    marker = tmp_path / "ran"
    (tmp_path / "base.py").write_text(MODEL_SOURCE.format(marker=str(marker)))
    spec = {
        "format": "jaxcal.extended_model/1", "base": "base.py:MODEL",
        "declared": ["p"],
        "added": [{"name": "bias", "channel": "additive", "target": "y1",
                   "nominal": 0.0, "low": -1.0, "high": 1.0, "unit": "-",
                   "scale": 0.1}],
    }  # fmt: skip
    path = tmp_path / "extended_model.json"
    path.write_text(json.dumps(spec))
    with pytest.raises(UntrustedCodeError) as err:
        jaxcal.models.load(str(path))
    assert str(path) in str(err.value) and "trust_code=True" in str(err.value)
    assert not marker.exists()
    model = jaxcal.models.load(str(path), trust_code=True)
    assert model.parameter_names == ("p", "bias") and marker.exists()


def test_a_data_files_engine_attribute_names_only_a_registered_model():
    from jaxcal.models.turbofan.training import file_model

    with pytest.raises(ValueError, match="never names code to run"):
        file_model({"attrs": {"engine": "os:getpid"}})


def test_the_npe_posterior_loads_with_weights_only(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("sbi")
    import torch

    from jaxcal.paper import npe

    cfg = npe.NPEConfig(
        max_samples=200, batch_size=50, max_epochs=2, stop_after_epochs=1,
        hidden_features=8, num_transforms=1, num_posterior_samples=20,
    )  # fmt: skip
    rng = np.random.default_rng(0)
    theta = rng.uniform(0, 1, (200, 1)).astype(np.float32)
    feats = (theta + 0.1 * rng.standard_normal((200, 1))).astype(np.float32)
    posterior, _ = npe.fit_npe(theta, feats, [0.0], [1.0], cfg, seed=0)
    path = npe.save_posterior(tmp_path / "post.pt", posterior, cfg)
    torch.load(path, weights_only=True)  # data only: no pickled code
    loaded = npe.load_posterior(path)
    a = npe.posterior_summary(posterior, feats[:10], cfg, seed=1)
    b = npe.posterior_summary(loaded, feats[:10], cfg, seed=1)
    np.testing.assert_array_equal(a["mean"], b["mean"])


def test_the_evaluate_command_line_refuses_a_received_run_without_trust_code(
    tmp_path, capsys
):
    from jaxcal.cli import evaluate

    marker = tmp_path / "ran"
    content = MODEL_SOURCE.format(marker=str(marker))
    run = _run_folder(tmp_path, _file_record(content), copy=content)
    assert evaluate.main([f"run={run}"]) == 2
    err = capsys.readouterr().err
    assert "toy_model.py" in err and "trust_code=true" in err
    assert not marker.exists()
    assert evaluate.parse_args([f"run={run}", "trust_code=true"])["trust_code"] is True
    with pytest.raises(ValueError, match="trust_code='maybe': expected a bool"):
        evaluate.parse_args([f"run={run}", "trust_code=maybe"])
