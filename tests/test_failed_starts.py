"""Failed starts leave nothing behind; bad output paths exit 2; stale temps go away.

Issue #12, item 2: ``train`` checks its config and data before it creates the run
folder, a folder left by an older version with only ``config.json`` does not block the
corrected command, the CLIs refuse an output path they cannot write before any work,
and the next write to a target removes the temporary files of writers killed mid-way
(never those of a live writer).
"""

import json
import os
import signal
import subprocess
import sys

import pytest
from support.synthetic_file import write_synthetic_ncmapss

from jaxcal.cli import evaluate
from jaxcal.cli.train import main as train_main
from jaxcal.cli.train import parse_args
from jaxcal.models.turbofan import training as turbofan_training
from jaxcal.models.turbofan.data.ncmapss_writer import NCMAPSSWriter
from jaxcal.runs.atomic import host_tag, make_temp, release_temp, write_atomic
from jaxcal.runs.folder import check_run_dir
from jaxcal.settings import check_output_path, config_to_dict
from jaxcal.training.config import resolve_config

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def data_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "synthetic.h5"
    return write_synthetic_ncmapss(path, dev_units=(1, 2, 3), test_units=(4, 5))


def _argv(runs, *extra):
    return [
        "dataset=ncmapss",
        "preset=smoke",
        f"output.runs_dir={runs}",
        "output.progress=false",
        "name=fix",
        "budget.num_chunks=1",
        *extra,
    ]


def test_failed_train_starts_leave_nothing_and_the_fixed_command_runs(
    data_file, tmp_path, capsys
):
    runs = tmp_path / "runs"
    run_dir = runs / "fix"
    # forgot path=: exit 2, no run folder
    assert train_main(_argv(runs)) == 2
    assert "path=<file.h5>" in capsys.readouterr().err
    assert not run_dir.exists()
    garbage = tmp_path / "garbage.h5"
    garbage.write_text("not hdf5")
    bad_starts = {
        "theta=HPT_eff": "theta must be distinct names",
        "sensors=bogus": "not in X_s_var",
        "dataset.val_units=4": "not dev units",
        f"path={garbage}": "not an HDF5 file",
        f"path={tmp_path / 'missing.h5'}": "not found",
    }
    for token, message in bad_starts.items():
        extra = [token] if token.startswith("path=") else [f"path={data_file}", token]
        assert train_main(_argv(runs, *extra)) == 2, token
        assert message in capsys.readouterr().err, token
        assert not run_dir.exists(), token
    # An older version left config.json of another config before failing: no block.
    run_dir.mkdir(parents=True)
    other = parse_args(_argv(runs, f"path={data_file}", "agent=sac"))
    (run_dir / "config.json").write_text(json.dumps(config_to_dict(other)))
    assert train_main(_argv(runs, f"path={data_file}", "dataset.stride=1")) == 0
    out = capsys.readouterr().out
    assert "held only the config.json of a failed start" in out
    assert "test units [4, 5]: theta RMSE" in out
    stored = json.loads((run_dir / "config.json").read_text())
    assert stored["agent"]["_type"] == "CLACConfig"
    assert (run_dir / "final.json").is_file()


def test_failed_data_generation_leaves_no_run_folder(tmp_path, monkeypatch, capsys):
    runs = tmp_path / "runs"
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    base = [
        "dataset=tiny",
        "preset=smoke",
        f"output.runs_dir={runs}",
        "output.progress=false",
        "name=gen",
    ]
    # a data path the generator could never write: refused before it starts
    assert train_main(base + [f"path={blocker}/tiny.h5"]) == 2
    assert "dataset.path=" in capsys.readouterr().err
    assert not runs.exists()
    calls = []

    def fake_generate(cfg, out, *, progress):  # the generator's two ways to fail
        calls.append(cfg.name)
        raise fake_generate.error

    monkeypatch.setattr(turbofan_training, "generate_dataset", fake_generate)
    for error, exit_code in ((RuntimeError("solver"), 1), (ValueError("bad"), 1)):
        fake_generate.error = error
        assert train_main(base + [f"path={tmp_path / 'data' / 'tiny.h5'}"]) == exit_code
        assert "generating" in capsys.readouterr().err
        assert not runs.exists()
    assert calls == ["tiny", "tiny"]
    # a preset that does not exist: bad arguments, before any generation
    nope = ["dataset.generate=nope", f"path={tmp_path / 'data' / 'tiny.h5'}"]
    assert train_main(base + nope) == 2
    assert "unknown dataset 'nope'" in capsys.readouterr().err
    assert calls == ["tiny", "tiny"] and not runs.exists()


def _config(runs):
    return resolve_config(["dataset=ncmapss", "path=x.h5", f"output.runs_dir={runs}"])


def test_check_run_dir_writes_nothing_and_tells_stale_from_real_runs(tmp_path):
    cfg = _config(tmp_path)
    other = resolve_config(["dataset=ncmapss", "path=y.h5"])
    run_dir = tmp_path / "runs" / "r"
    assert check_run_dir(run_dir, cfg) == "new" and not run_dir.exists()
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(config_to_dict(other)))
    (run_dir / f".config.json.{host_tag()}.1.abcdefgh.tmp").write_text("")
    assert check_run_dir(run_dir, cfg) == "stale"
    (run_dir / "metrics.jsonl").write_text("")
    with pytest.raises(ValueError, match=r"different config \(dataset.path"):
        check_run_dir(run_dir, cfg)
    (run_dir / "config.json").write_text(json.dumps(config_to_dict(cfg)))
    assert check_run_dir(run_dir, cfg) == "resume"
    (tmp_path / "runs" / "f").write_text("")
    with pytest.raises(ValueError, match="output.runs_dir/name=.* is a file"):
        check_run_dir(tmp_path / "runs" / "f", cfg)


def test_check_output_path_names_the_field_and_the_path(tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert check_output_path(str(tmp_path / "new" / "deep" / "x.h5"), "out")
    assert check_output_path(str(tmp_path / "new"), "out", folder=True)
    bad = {
        ("", False): "out='': expected a file path",
        ("  ", True): "expected a folder path, got an empty one",
        (str(tmp_path), False): "is a folder; expected a file path",
        (str(blocker), True): "is a file; expected a folder path",
        (str(blocker / "sub" / "x.h5"), False): "is a file, so nothing can be created",
    }
    for (path, folder), message in bad.items():
        with pytest.raises(ValueError, match=message):
            check_output_path(path, "out", folder=folder)
    monkeypatch.setattr(os, "access", lambda path, mode: False)
    with pytest.raises(ValueError, match=r"out=.*x.h5.*is not writable"):
        check_output_path(str(tmp_path / "x.h5"), "out")


def test_evaluate_refuses_a_run_folder_it_cannot_write_before_the_work(
    tmp_path, monkeypatch, capsys
):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert evaluate.main([f"run={blocker}"]) == 2
    assert "run=" in capsys.readouterr().err
    monkeypatch.setattr(os, "access", lambda path, mode: False)
    assert evaluate.main([f"run={tmp_path}"]) == 2
    assert "is not writable" in capsys.readouterr().err


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_a_write_removes_only_the_temps_of_dead_writers_of_that_target(tmp_path):
    target = tmp_path / "final.json"
    host, dead = host_tag(), _dead_pid()
    own_live_fd, own_live = make_temp(target)  # this process is writing it now
    os.close(own_live_fd)
    names = {
        "dead": f".final.json.{host}.{dead}.abcdefgh.tmp",
        "own_left": f".final.json.{host}.{os.getpid()}.k_2m9x0a.tmp",
        "parent": f".final.json.{host}.{os.getppid()}.abcdefgh.tmp",
        "init": f".final.json.{host}.1.abcdefgh.tmp",
        "other_host": f".final.json.elsewhere-{host}.{dead}.abcdefgh.tmp",
        "other_target": f".final.json.old.{host}.{dead}.abcdefgh.tmp",
        "legacy": ".final.json.abcdefgh.tmp",
    }
    for name in names.values():
        (tmp_path / name).write_text("partial")
    write_atomic(target, "{}\n")
    left = {p.name for p in tmp_path.iterdir()}
    assert target.read_text() == "{}\n"
    assert names["dead"] not in left and names["own_left"] not in left
    for kept in ("parent", "init", "other_host", "other_target", "legacy"):
        assert names[kept] in left, kept
    assert os.path.basename(own_live) in left  # a live writer's file is never touched
    release_temp(own_live)
    assert not os.path.exists(own_live)


def test_a_killed_ncmapss_writer_leaves_a_temp_the_next_write_removes(tmp_path):
    target = tmp_path / "data.h5"
    code = (
        "import os, signal, sys\n"
        "from jaxcal.models.turbofan.data.ncmapss_writer import NCMAPSSWriter\n"
        "with NCMAPSSWriter(sys.argv[1]):\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(target)],
        cwd=REPO,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
        timeout=120,
        check=False,
    )
    assert proc.returncode == -signal.SIGKILL
    leftover = list(tmp_path.glob(".data.h5.*.tmp"))
    assert len(leftover) == 1 and not target.exists()
    write_synthetic_ncmapss(target, dev_units=(1,), test_units=(2,))
    assert target.is_file() and list(tmp_path.glob(".data.h5.*.tmp")) == []
    # a writer that fails cleanly removes its own temp file as before
    with pytest.raises(RuntimeError), NCMAPSSWriter(target):
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.h5"]


def test_a_writer_that_fails_midway_leaves_the_old_file_and_no_temp(tmp_path):
    # the one atomic writer with a writer callback (a figure, a Parquet table)
    from jaxcal.runs.atomic import write_atomic_with

    target = tmp_path / "result.parquet"
    write_atomic_with(target, lambda f: f.write(b"old"))

    def half(f):
        f.write(b"half a ")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_atomic_with(target, half)
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["result.parquet"]
