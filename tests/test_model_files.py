"""``model=file.py:attr`` that does not give a model (issue 25): a syntax error, an
exception at import or in the factory, a missing attribute, something else than a
model. Each is a ValueError naming the file (and line), so every command line taking
``model=`` prints one line and exits 2 instead of a raw traceback and exit 1."""

import subprocess
import sys

import pytest

import jaxcal

GOOD = (
    "import jax.numpy as jnp, jaxcal\n"
    "model = jaxcal.Model.from_function(lambda w, t: w * t, conditions=('u',),"
    " parameters={'k': (1.0, 0.0, 2.0)}, outputs=('y',))\n"
)
FILES = {
    "syntax": ("x = 1\ndef broken(:\n    pass\n", "model", r"line 2: syntax error"),
    "raises": (
        "x = 1\nraise RuntimeError('no licence server')\n",
        "model",
        r"raised RuntimeError: no licence server \(.*bad.py, line 2\)",
    ),
    "exits": ("import sys\nsys.exit(3)\n", "model", r"raised SystemExit: 3"),
    "factory": (
        "def make():\n    return {}['missing']\n",
        "make",
        r"calling make\(\) raised KeyError: 'missing' \(.*bad.py, line 2\)",
    ),
    "bad-model": (
        "import jaxcal\n"
        "m = jaxcal.Model.from_function(lambda w, t: w, conditions=('a',),\n"
        "    parameters={'a': (1.0, 0.0, 2.0)}, outputs=('y',))\n",
        "m",
        r"'a' is both a condition and a parameter.*line 2\)",
    ),
    "missing": ("x = 1\n", "model", r"bad.py has no attribute 'model'"),
    "not-a-model": ("x = 1\n", "x", r"neither a jaxcal.Model.*\(it is a int\)"),
    "returns-other": (
        "def make():\n    return 3\n",
        "make",
        r"calling make\(\) returned a int",
    ),
}


@pytest.mark.parametrize("case", sorted(FILES))
def test_a_model_file_that_gives_no_model_is_a_value_error(tmp_path, case):
    source, attr, match = FILES[case]
    path = tmp_path / "bad.py"
    path.write_text(source)
    before = set(sys.modules)
    with pytest.raises(ValueError, match=match) as err:
        jaxcal.models.load(f"{path}:{attr}")
    assert str(err.value).startswith(f"model='{path}:{attr}'")
    if case in ("syntax", "raises", "exits", "bad-model"):  # a half-run module
        assert "_jaxcal_user_model_bad" not in set(sys.modules) - before  # not kept


def test_a_good_model_file_still_loads(tmp_path):
    path = tmp_path / "good.py"
    path.write_text(GOOD)
    assert jaxcal.models.load(f"{path}:model").parameter_names == ("k",)


def test_a_module_that_raises_at_import_is_a_value_error(tmp_path, monkeypatch):
    (tmp_path / "raising_model_mod.py").write_text("raise OSError('disk gone')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ValueError, match=r"importing raising_model_mod raised OSError"):
        jaxcal.models.load("raising_model_mod:model")


@pytest.fixture()
def syntax_error_file(tmp_path):
    path = tmp_path / "bad.py"
    path.write_text(FILES["syntax"][0])
    data = tmp_path / "data.csv"
    data.write_text("u,y\n1.0,1.0\n2.0,2.0\n")
    return path, data


def test_train_exits_2_with_one_line(syntax_error_file, tmp_path, capsys):
    from jaxcal.cli.train import main as train

    path, data = syntax_error_file
    runs = tmp_path / "runs"
    assert (
        train([f"model={path}:model", f"data={data}", f"output.runs_dir={runs}"]) == 2
    )
    err = capsys.readouterr().err
    assert f"{path}, line 2: syntax error" in err and "Traceback" not in err


def test_diagnose_process_exits_2_without_a_traceback(syntax_error_file):
    path, data = syntax_error_file
    proc = subprocess.run(
        [sys.executable, "-m", "jaxcal.diagnose", f"model={path}:model",
         f"data={data}", "calibrate=k", f"out={path.parent / 'report'}"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"jaxcal.diagnose: model='{path}:model': {path}, line 2: syntax error: "
        "invalid syntax"
    ]
