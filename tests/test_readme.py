"""The two examples of calibrate's front door run verbatim, once with each method their
comment names: README's "Bring your own model" (repeated at the top of
docs/your-model.md) and docs/memory.md's model with memory.

tests/test_docs.py runs or compiles every other code block of README.md and docs/;
it leaves the blocks with such a call (:data:`CALL`) to this file (:data:`RUN`).
"""

import pathlib
import re

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
CALL = re.compile(r'^(result = jaxcal\.calibrate\(.*method=)"(\w+)"(\).*#(.*))$', re.M)
# (file, section title) of each example run here with each method
TANK = ("README.md", "Bring your own model")
MEMORY = ("docs/memory.md", "Models with memory")


def _block(path: str, title: str) -> str:
    """The one Python block of the section (``##`` or the page's ``#``) ``title``."""
    text = (ROOT / path).read_text()
    section = re.split(rf"^#+ {re.escape(title)}\n", text, flags=re.M)[1]
    section = re.split(r"^## ", section, flags=re.M)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1, (path, title)
    return blocks[0]


# the block sources run here; test_docs.py compiles them and runs the rest
RUN = (_block(*TANK), _block(*MEMORY))


def _methods(block: str) -> list[str]:
    """The method of the block's call and those its comment names (quoted)."""
    (call,) = CALL.findall(block)
    return [call[1], *re.findall(r'"(\w+)"', call[3])]


def _cases(where):
    return [pytest.param(m, id=m) for m in _methods(_block(*where))]


def _run(where, method: str) -> object:
    block = _block(*where)
    source = CALL.sub(lambda m: f'{m[1]}"{method}"{m[3]}', block)
    assert source.count(f'method="{method}"') == 1
    namespace = {}
    exec(compile(source, where[0], "exec"), namespace)  # noqa: S102
    return namespace["result"]


def test_each_block_names_the_methods_that_run_with_its_call():
    for where in (TANK, MEMORY):
        assert _methods(_block(*where)) == ["ukf", "ekf", "ls", "e2e"], where
    lines = _block(*TANK).strip().splitlines()
    assert 15 <= len(lines) <= 25


def test_your_model_page_opens_with_the_readme_example():
    page = (ROOT / "docs/your-model.md").read_text()
    first = re.search(r"```python\n(.*?)```", page, flags=re.S)[1]
    assert first == _block(*TANK)


@pytest.mark.parametrize("method", _cases(TANK))
def test_bring_your_own_model_block_runs(capsys, method):
    result = _run(TANK, method)
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


@pytest.mark.parametrize("method", _cases(MEMORY))
def test_models_with_memory_block_runs(capsys, method):
    result = _run(MEMORY, method)
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
