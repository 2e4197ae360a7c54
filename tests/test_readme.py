"""The README's "Bring your own model" example runs verbatim."""

import pathlib
import re

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_bring_your_own_model_block_runs(capsys):
    text = README.read_text()
    section = text.split("## Bring your own model", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1
    lines = blocks[0].strip().splitlines()
    assert 15 <= len(lines) <= 25
    namespace = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102
    result = namespace["result"]
    assert result.theta.shape == (300, 2) and result.valid.all()
    # the last row's estimate is within 3 std of the truth (leak 1.3, loss 0.2)
    err = abs(result.theta[-1] - [1.3, 0.2]) / result.theta_std[-1]
    assert (err < 3).all(), err
    assert "+-" in capsys.readouterr().out


def test_models_with_memory_block_runs(capsys):
    text = README.read_text()
    section = text.split("## Models with memory", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1
    namespace = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102
    result = namespace["result"]
    assert result.theta.shape == (400, 2) and result.states.shape == (400, 1)
    err = abs(result.theta[-1] - [3.0, 1.4]) / result.theta_std[-1]
    assert (err < 3).all(), err
    assert "state" in capsys.readouterr().out
