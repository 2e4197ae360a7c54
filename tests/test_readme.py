"""The README's "Bring your own model" and "Models with memory" examples run verbatim,
once with each method their comment names."""

import pathlib
import re

import numpy as np
import pytest

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
CALL = re.compile(r'^(result = jaxcal\.calibrate\(.*method=)"(\w+)"(\).*#(.*))$', re.M)


def _block(title: str) -> str:
    section = README.read_text().split(f"## {title}", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1
    return blocks[0]


def _methods(block: str) -> list[str]:
    """The method of the block's call and those its comment names (quoted)."""
    (call,) = CALL.findall(block)
    return [call[1], *re.findall(r'"(\w+)"', call[3])]


def _cases(title):
    return [pytest.param(m, id=m) for m in _methods(_block(title))]


def _run(title: str, method: str) -> object:
    block = _block(title)
    source = CALL.sub(lambda m: f'{m[1]}"{method}"{m[3]}', block)
    assert source.count(f'method="{method}"') == 1
    namespace = {}
    exec(compile(source, "README.md", "exec"), namespace)  # noqa: S102
    return namespace["result"]


def test_each_block_names_the_methods_that_run_with_its_call():
    for title in ("Bring your own model", "Models with memory"):
        assert _methods(_block(title)) == ["ukf", "ls", "e2e"], title
    lines = _block("Bring your own model").strip().splitlines()
    assert 15 <= len(lines) <= 25


@pytest.mark.parametrize("method", _cases("Bring your own model"))
def test_bring_your_own_model_block_runs(capsys, method):
    result = _run("Bring your own model", method)
    assert result.method == method
    assert result.theta.shape == (300, 2) and result.valid.all()
    out = capsys.readouterr().out
    assert "leak = " in out and "loss = " in out
    assert np.isfinite(result.theta).all()
    if result.theta_std is None:  # E2E: a point estimate
        assert "±" not in out
        return
    # the last row's estimate is within 3 std of the truth (leak 1.3, loss 0.2)
    err = abs(result.theta[-1] - [1.3, 0.2]) / result.theta_std[-1]
    assert (err < 3).all(), err
    assert "±" in out


@pytest.mark.parametrize("method", _cases("Models with memory"))
def test_models_with_memory_block_runs(capsys, method):
    result = _run("Models with memory", method)
    assert result.method == method
    assert result.theta.shape == (400, 2)
    out = capsys.readouterr().out
    assert "tau = " in out and "gain = " in out
    if method in ("ukf", "ls"):  # the filtered / the window fit's simulated state
        assert result.states.shape == (400, 1) and "state z = " in out
    if result.theta_std is None:  # E2E: a point estimate
        assert "±" not in out
        return
    err = abs(result.theta[-1] - [3.0, 1.4]) / result.theta_std[-1]
    assert (err < 3).all(), err
