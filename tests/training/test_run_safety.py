"""Runs confined to ``runs/``, locked while they train, and self-contained (issue 25).

One run of a small static model, defined in a file of its own (so the tests can edit
and move it), is trained once for the module with ``dynamics=physics``: its tracking
then runs the model itself, so a run that followed edits of the file would show it.
While it trains, a second ``python -m jaxcal.train`` of the same name is started.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import warnings
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.calibrators.methods.policy.run_model import check_run_model
from jaxcal.cli.train import main as train_main
from jaxcal.deploy import adopt_model_file, load_run
from jaxcal.models import load
from jaxcal.runs.lock import LOCK_FILE, RunInUseError, hold_run
from jaxcal.training import kept_policy, pipeline
from jaxcal.training.config import OutputConfig, TrainConfig, resolve_config
from jaxcal.training.model_source import (
    load_run_model,
    model_source,
    recorded_source,
)

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ENV = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": REPO}
SOURCE = textwrap.dedent(
    """
    import jax.numpy as jnp
    import jaxcal

    def toy(w, theta):
        a, b = w[0], w[1]
        p, q = theta[0], theta[1]
        return jnp.stack([p * a + q * b, p * q + 0.5 * a, p - q * a * b])

    MODEL = jaxcal.Model.from_function(
        toy,
        conditions={"a": "m", "b": "s"},
        parameters={"p": (1.0, 0.5, 2.0, "-"), "q": (0.5, 0.1, 1.0, "-")},
        outputs=("y1", "y2", "y3"),
        name="toy",
    )
    """
)
# What the file becomes after "a later edit" (y1 three times larger).
EDITED = SOURCE.replace("p * a + q * b", "3.0 * p * a + q * b")
HOLDER = (
    "import sys, time\n"
    "from jaxcal.runs.lock import hold_run\n"
    "with hold_run(sys.argv[1]):\n"
    "    print('held', flush=True)\n"
    "    time.sleep(600)\n"
)


def _frame(model) -> pd.DataFrame:
    """6 units of 30 rows, p and q drifting slowly."""
    rng = np.random.default_rng(0)
    rows = []
    for unit in range(1, 7):
        w = np.stack([rng.uniform(0.5, 1.5, 30), rng.uniform(0.2, 1.0, 30)], 1)
        theta = np.stack([1.0 + 0.02 * unit + 0.002 * np.arange(30),
                          np.full(30, 0.4 + 0.01 * unit)], 1)  # fmt: skip
        x = np.stack([np.asarray(model.evaluate(jnp.asarray(a), jnp.asarray(t))[0])
                      for a, t in zip(w, theta, strict=True)])  # fmt: skip
        x = x + 1e-3 * rng.standard_normal(x.shape)
        rows.append(pd.DataFrame({"unit": unit, "time": np.arange(30), "a": w[:, 0],
                                  "b": w[:, 1], "y1": x[:, 0], "y2": x[:, 1],
                                  "y3": x[:, 2]}))  # fmt: skip
    return pd.concat(rows, ignore_index=True)


def _argv(files, *extra):
    return [
        f"model={files.model}:MODEL",
        f"data={files.csv}",
        "theta=p,q",
        "preset=smoke",
        "dynamics=physics",
        f"output.runs_dir={files.runs}",
        "output.progress=false",
        *extra,
    ]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("safety")
    model_file = root / "toy_model.py"
    model_file.write_text(SOURCE)
    csv = root / "toy.csv"
    _frame(load(f"{model_file}:MODEL")).to_csv(csv, index=False)
    return SimpleNamespace(root=root, model=model_file, csv=csv, runs=root / "runs")


@pytest.fixture(scope="module")
def trained(files):
    """The run ``toy``; while its policy trains, a second training of the name is
    started as a separate command (its exit code and stderr are kept)."""
    second = {}
    real = kept_policy.train_policy

    def train_policy_beside_a_twin(*args, **kwargs):
        proc = subprocess.run(
            [sys.executable, "-m", "jaxcal.train", *_argv(files, "name=toy")],
            capture_output=True, text=True, env=ENV, cwd=files.root, timeout=600,
        )  # fmt: skip
        second.update(code=proc.returncode, err=proc.stderr)
        return real(*args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(kept_policy, "train_policy", train_policy_beside_a_twin)
        assert train_main(_argv(files, "name=toy")) == 0
    return SimpleNamespace(run=files.runs / "toy", second=second)


def _rmse(result, csv) -> float:
    x = pd.read_csv(csv)[["y1", "y2", "y3"]].to_numpy()
    return float(np.sqrt(np.mean((result.xhat - x) ** 2)))


@pytest.mark.parametrize("name", ["../x", "/tmp/x", "a/b", "a\\b", "..", ".hidden"])
def test_run_names_outside_the_runs_folder_are_refused(tmp_path, capsys, name):
    runs = tmp_path / "runs"
    argv = ["model=heat_exchanger", f"data={tmp_path / 'no.csv'}",
            f"output.runs_dir={runs}", f"name={name}"]  # fmt: skip
    assert train_main(argv) == 2
    err = capsys.readouterr().err
    assert f"name={name!r}" in err and "one folder name inside output.runs_dir" in err
    assert not any(tmp_path.iterdir())  # nothing written, inside runs/ or beside it
    with pytest.raises(ValueError, match="one folder name"):
        TrainConfig(output=OutputConfig(name=name))


def test_a_derived_run_name_is_checked_too():
    with pytest.raises(ValueError, match=r"name \(derived.*'\.\./x-clac"):
        resolve_config(["dataset.name=../x", "data=f.csv", "model=heat_exchanger"])


def test_a_second_training_of_a_run_in_use_exits_2_and_nothing_interleaves(trained):
    assert trained.second["code"] == 2, trained.second["err"]
    err = trained.second["err"]
    assert "is in use" in err and f"pid {os.getpid()}" in err, err
    assert "Traceback" not in err
    steps = [json.loads(line)["step"] for line in open(trained.run / "metrics.jsonl")]
    assert steps == sorted(set(steps)) == [1, 2]
    final = json.loads((trained.run / "final.json").read_text())
    assert final["chunks"] == 2 and final["sessions"] == 1
    assert (trained.run / LOCK_FILE).read_text() == ""  # released: no holder left


def _start_holder(run_dir):
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(run_dir)],
        stdout=subprocess.PIPE, text=True, env=ENV,
    )  # fmt: skip
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_training_that_loses_the_race_for_the_lock_exits_2(files, tmp_path, capsys):
    """Both trainings passed the early check; the lock, taken before the first write,
    decides: the loser exits 2 naming the holder and writes nothing."""
    runs = tmp_path / "runs"
    holder = []
    real = pipeline.read_run_data

    def read_then_lose_the_race(*args, **kwargs):
        data = real(*args, **kwargs)
        holder.append(_start_holder(runs / "race"))
        return data

    argv = [a for a in _argv(files, "name=race") if not a.startswith("output.runs")]
    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(pipeline, "read_run_data", read_then_lose_the_race)
            assert train_main([*argv, f"output.runs_dir={runs}"]) == 2
        err = capsys.readouterr().err
        assert "is in use" in err and f"pid {holder[0].pid}" in err
        assert sorted(p.name for p in (runs / "race").iterdir()) == [LOCK_FILE]
    finally:
        for proc in holder:
            proc.kill()
            proc.wait()


def test_a_killed_training_does_not_keep_its_lock(tmp_path):
    run_dir = tmp_path / "runs" / "r"
    proc = _start_holder(run_dir)
    with pytest.raises(RunInUseError, match=f"pid {proc.pid}"):
        with hold_run(run_dir):
            pass
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    with hold_run(run_dir):  # the kernel released it with the process
        holder = json.loads((run_dir / LOCK_FILE).read_text())
        assert holder["pid"] == os.getpid()
        with pytest.raises(RunInUseError, match=f"pid {os.getpid()}"):
            with hold_run(run_dir):  # a second holder in this process: refused too
                pass


def test_a_run_keeps_a_copy_of_its_model_file(trained, files):
    data = json.loads((trained.run / "data.json").read_text())
    source = data["model_source"]
    assert source["kind"] == "file" and source["attr"] == "MODEL"
    assert source["origin"] == str(files.model)
    copy = trained.run / source["file"]
    assert copy.parent.name == "model" and copy.read_text() == SOURCE
    import hashlib

    assert source["sha256"] == hashlib.sha256(SOURCE.encode()).hexdigest()


def test_a_run_loads_after_its_model_file_moved(trained, files):
    moved = files.model.with_name("moved.py")
    files.model.rename(moved)
    try:
        run = load_run(trained.run)
        x, _ = run.problem.model.evaluate(jnp.array([1.0, 0.5]), jnp.array([1.0, 0.4]))
        np.testing.assert_allclose(x, [1.2, 0.9, 0.8], rtol=1e-6)
    finally:
        moved.rename(files.model)


def test_a_run_does_not_follow_later_edits_of_its_model_file(trained, files):
    model = load(f"{files.model}:MODEL")
    before = jaxcal.calibrate(model, files.csv, "policy", run=trained.run)
    files.model.write_text(EDITED)
    try:
        after = jaxcal.calibrate(model, files.csv, "policy", run=trained.run)
        np.testing.assert_array_equal(after.xhat, before.xhat)
        np.testing.assert_array_equal(after.theta, before.theta)
        edited = load(f"{files.model}:MODEL")
        with pytest.raises(ValueError, match=r"differs: at the probe point .* 'y1'"):
            jaxcal.calibrate(edited, files.csv, "policy", run=trained.run)
    finally:
        files.model.write_text(SOURCE)
    assert _rmse(before, files.csv) < 0.5


def test_a_resume_refuses_a_model_file_changed_since_the_run_started(
    trained, files, capsys
):
    files.model.write_text(EDITED)
    try:
        assert train_main(_argv(files, "name=toy")) == 2
    finally:
        files.model.write_text(SOURCE)
    assert "a resume would train the policy on another model" in capsys.readouterr().err
    final = json.loads((trained.run / "final.json").read_text())
    assert final["sessions"] == 1  # nothing of the run was touched


def test_calibrate_refuses_a_model_that_is_not_the_runs(trained, files):
    def other(w, theta):
        return jnp.stack([5 * theta[0] * w[0], theta[1], w[1]])

    spec = dict(
        conditions={"a": "m", "b": "s"},
        parameters={"p": (1.0, 0.5, 2.0, "-"), "q": (0.5, 0.1, 1.0, "-")},
        outputs=("y1", "y2", "y3"),
    )
    wrong = jaxcal.Model.from_function(other, **spec, name="other")
    with pytest.raises(ValueError, match="trained on model 'toy'.*'other'.*differs"):
        jaxcal.calibrate(wrong, files.csv, "policy", run=trained.run)
    # the same function under another name: used, with a warning
    same = load(f"{files.model}:MODEL")
    renamed = jaxcal.Model.from_function(
        lambda w, th: same.evaluate(w, th)[0], **spec, name="renamed"
    )
    with pytest.warns(UserWarning, match="named 'renamed' but has the same"):
        result = jaxcal.calibrate(renamed, files.csv, "policy", run=trained.run)
    assert result.valid.all()


def _copy_run(trained, tmp_path, **changes):
    copy = tmp_path / "copied"
    shutil.copytree(trained.run, copy)
    data = json.loads((copy / "data.json").read_text())
    data.update(changes)
    data = {k: v for k, v in data.items() if v is not None}
    (copy / "data.json").write_text(json.dumps(data))
    return copy


@pytest.mark.parametrize(
    "source",
    [
        None,  # the older layout: a bare model_spec naming a file outside the run
        {"kind": "file", "file": "../evil.py", "attr": "MODEL", "sha256": "0"},
        {"kind": "file", "file": "EVIL", "attr": "MODEL", "sha256": "0"},
        {"kind": "registered", "name": "EVIL:MODEL"},
        {"kind": "module", "module": "EVIL", "attr": "MODEL"},
    ],
)
def test_loading_a_run_never_imports_a_path_outside_it(trained, tmp_path, source):
    evil = tmp_path / "evil.py"
    marker = tmp_path / "ran"
    evil.write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    if source is not None:
        source = {k: str(evil) if v == "EVIL" else v for k, v in source.items()}
    run = _copy_run(trained, tmp_path, model_spec=f"{evil}:MODEL", model_source=source)
    with pytest.raises(ValueError, match="outside|not a model this jaxcal can load"):
        load_run(run)
    assert not marker.exists()


def test_an_edited_model_copy_is_refused(trained, tmp_path):
    run = _copy_run(trained, tmp_path)
    with open(run / "model" / "toy_model.py", "a") as f:
        f.write("\n# edited\n")
    with pytest.raises(ValueError, match="edited after training"):
        load_run(run)


def test_an_older_run_adopts_a_model_file_it_is_given(trained, files, tmp_path):
    run = _copy_run(trained, tmp_path, model_source=None)
    shutil.rmtree(run / "model")
    with pytest.raises(ValueError, match="adopt_model_file"):
        load_run(run)
    assert adopt_model_file(run, files.model).name == "toy"
    assert load_run(run).model_source["origin"] == str(files.model)
    with pytest.raises(ValueError, match="nothing to adopt"):
        adopt_model_file(run, files.model)


def test_what_a_run_records_of_a_registered_or_module_model():
    record = model_source("heat_exchanger").record
    assert record == {"kind": "registered", "name": "heat_exchanger",
                      "version": jaxcal.__version__}  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_run_model(".", {"model_source": record}).name == "heat_exchanger"
    old = {**record, "version": "0.0.1"}
    with pytest.warns(UserWarning, match="jaxcal 0.0.1's 'heat_exchanger'"):
        load_run_model(".", {"model_source": old})
    spec = "jaxcal.models.heat_exchanger:heat_exchanger_model"
    record = model_source(spec).record
    assert record["kind"] == "module" and len(record["sha256"]) == 64
    changed = {"model_source": {**record, "sha256": "0" * 64}}
    with pytest.raises(ValueError, match="trust_code=True"):  # code: needs consent
        load_run_model(".", changed)
    with pytest.warns(UserWarning, match="differs"):
        load_run_model(".", changed, trust_code=True)
    with pytest.raises(ValueError, match="put the model in a file"):
        model_source("__main__:MODEL")
    # a run of the older layout: a registered name is its record, a file none
    assert recorded_source({"model_spec": "cmapss"})["name"] == "cmapss"
    assert recorded_source({"model_spec": "/somewhere/m.py:MODEL"}) is None


def test_the_model_check_compares_names_and_steps_of_a_stateful_model():
    def lag(z, w, theta):
        a = jnp.exp(-1.0 / theta[0])
        z = a * z + (1 - a) * w[0]
        return z, jnp.stack([theta[1] * z[0], w[0] - z[0]])

    def build(step, states=("z",), name="lag"):
        return jaxcal.Model.from_step(
            step, init_state=lambda w0, theta: w0[:1], states=states,
            conditions=("u",), outputs=("y1", "y2"), name=name,
            parameters={"tau": (5.0, 2.0, 10.0, "s"), "gain": (1.0, 0.5, 2.0)},
        )  # fmt: skip

    own = build(lag)
    problem = SimpleNamespace(
        model=own, input_range=None, theta_base=np.array([5.0, 1.0]),
        theta_low=np.array([2.0, 0.5]), theta_high=np.array([10.0, 2.0]),
        theta_index=(0, 1),
    )  # fmt: skip
    run = SimpleNamespace(run_dir="runs/lag", problem=problem, model_source=None)
    check_run_model(run, build(lag))  # the same model, built again

    def slower(z, w, theta):  # differs only in how the state moves
        return lag(z, w, theta.at[0].multiply(2.0))

    with pytest.raises(ValueError, match="step 2 from the initial state"):
        check_run_model(run, build(slower))
    with pytest.raises(ValueError, match=r"state_names are \['z'\].*\['s'\]"):
        check_run_model(run, build(lag, states=("s",)))
