"""Every command line answers a misspelt key with the closest valid one, in one line
(exit code 2), and prints its usage on ``--help`` / ``-h`` (exit code 0)."""

import importlib

import pytest

from jaxcal.cli.args import with_closest_key
from jaxcal.settings import UnknownKeyError

# (command line, argv with a typo, the key it should suggest)
TYPOS = [
    ("train", ["dataset=tiny", "sead=1"], "seed"),
    ("train", ["dataset=tiny", "outpts=T24"], "outputs"),  # a key of the usage only
    ("train", ["agent.actor_rl=1e-4"], "agent.actor_lr"),  # a nested field
    ("evaluate", ["rn=runs/x"], "run"),
    ("diagnose", ["data=x.csv", "calibrat=HPC_eff_mod"], "calibrate"),
    ("fleet", ["data=x.csv", "out=o.h5", "methd=ls"], "method"),
    ("generate", ["dataset=tiny", "sead=3"], "seed"),
    ("generate", ["datset=tiny"], "dataset"),  # named, not "missing dataset"
    ("validate", ["engin=agtf30"], "engine"),
    ("validate", ["--engin", "agtf30"], "--engine"),  # a flag spelling
    ("bench", ["engine", "batchh=8"], "batch"),
    ("prognose", ["train=a.csv", "test=b.csv", "out=o", "boundry=x:1"], "boundary"),
]


@pytest.mark.parametrize(("tool", "argv", "closest"), TYPOS)
def test_a_typo_gets_one_line_with_the_closest_key(tool, argv, closest, capsys):
    main = importlib.import_module(f"jaxcal.cli.{tool}").main
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert f"(did you mean {closest!r}?)" in lines[0]


@pytest.mark.parametrize(
    "tool",
    [
        "train",
        "evaluate",
        "diagnose",
        "fleet",
        "generate",
        "validate",
        "bench",
        "prognose",
    ],
)
@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_prints_the_usage_and_exits_0(tool, flag, capsys):
    main = importlib.import_module(f"jaxcal.cli.{tool}").main
    assert main([flag]) == 0
    out, err = capsys.readouterr()
    assert f"usage: python -m jaxcal.{tool}" in out and err == ""
    assert "malformed" not in out


def test_a_key_like_nothing_keeps_the_usage_and_no_hint(capsys):
    from jaxcal.cli.evaluate import main

    assert main(["zzzzzz=1"]) == 2
    err = capsys.readouterr().err
    assert "did you mean" not in err and "usage: python -m jaxcal.evaluate" in err
    assert "valid keys: run, split" in err


def test_the_hint_is_found_through_a_wrapping_error():
    try:
        try:
            raise UnknownKeyError("unknown key 'sed'; valid: seed", "sed", ["seed"])
        except ValueError as err:
            raise ValueError(f"{err} (and: out)") from None
    except ValueError as wrapped:
        message = with_closest_key(wrapped, "usage: x [out=PATH]")
    assert message == "unknown key 'sed' (did you mean 'seed'?); valid: seed (and: out)"
    plain = ValueError("seed='x': expected an integer")
    assert with_closest_key(plain, "usage: x seed=N") == str(plain)
