"""The docs say what the code does: every ``result.<name>`` the pages name is an
attribute of a result class, and every ``name=`` option they name in inline code is a
key that some entry point takes (issue 42: ``docs/fleet.md`` passed on a
``result.noise_std`` that did not exist).

Code blocks are run by tests/test_docs.py; this reads the prose around them.
"""

import dataclasses
import inspect
import pathlib
import re
import typing

import jax
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^```.*?^```\s*$", re.M | re.S)
RESULT_ATTR = re.compile(r"(?<![\w.])result\.([A-Za-z_]\w*)")
INLINE_KEY = re.compile(r"`([A-Za-z_][\w.]*)=")
# file names that read like an attribute (``result.parquet``)
FILE_SUFFIXES = {"parquet", "csv", "h5", "json", "md", "png"}
# keys the pages name on purpose though no parser takes them, each with its reason
NOT_KEYS = {
    "theta_scale": "docs/fleet.md says the old key is gone (and the fleet says so)",
    "key": "the placeholder of key=value",
    "skip": "experiments/paper.py's own argument, not the package's",
}


def _prose(page: pathlib.Path) -> str:
    return FENCE.sub("", page.read_text())


def _mentions(pattern: re.Pattern) -> list[tuple[str, str]]:
    return sorted(
        {
            (m[1], str(page.relative_to(ROOT)))
            for page in PAGES
            for m in pattern.finditer(_prose(page))
        }
    )


def _result_attributes() -> set[str]:
    from jaxcal.calibrators.front.result import CalibrationResult
    from jaxcal.diagnosis.pipeline import DiagnosisResult

    names = {f.name for f in dataclasses.fields(CalibrationResult)}
    for cls in (CalibrationResult, DiagnosisResult):
        names |= {n for n in dir(cls) if not n.startswith("_")}
    return names | set(DiagnosisResult._fields)


def _dotted_keys(cfg, prefix: str = "") -> set[str]:
    """Every ``field`` / ``group.field`` of a (nested) dataclass config, following
    the dataclass members of each field's annotation and its default's type."""
    keys = set()
    hints = typing.get_type_hints(cfg if isinstance(cfg, type) else type(cfg))
    for f in dataclasses.fields(cfg):
        keys.add(prefix + f.name)
        kinds = {a for a in typing.get_args(hints[f.name]) or (hints[f.name],)}
        default = getattr(cfg, f.name, None) if not isinstance(cfg, type) else None
        if dataclasses.is_dataclass(default):
            kinds.add(type(default))
        for kind in kinds:
            if isinstance(kind, type) and dataclasses.is_dataclass(kind):
                keys |= _dotted_keys(kind, prefix + f.name + ".")
    return keys


def _valid_keys() -> set[str]:
    from jaxcal.calibrators.front.door import _READER_OPTIONS, calibrate
    from jaxcal.calibrators.methods import METHODS, options_of
    from jaxcal.cli import (
        bench,
        diagnose,
        evaluate,
        fleet,
        generate,
        prognose,
        train,
        validate,
    )  # fmt: skip
    from jaxcal.cli.args import _USAGE_KEY
    from jaxcal.fleet.method import OPTION_PREFIXES
    from jaxcal.model import Model
    from jaxcal.models.turbofan.data.dataset_configs import DatasetConfig
    from jaxcal.training.config import PRESET_NAMES, agent_presets, resolve_config

    keys = _dotted_keys(resolve_config([]))
    for preset in PRESET_NAMES:
        for agent in agent_presets(preset).values():
            keys |= _dotted_keys(agent, "agent.")
    for cfg in (
        diagnose.DiagnoseConfig, fleet.FleetConfig, DatasetConfig, bench.BenchArgs,
        validate.ValidateArgs, prognose.PrognoseConfig,
    ):  # fmt: skip
        keys |= _dotted_keys(cfg)
    keys |= set(evaluate.KEYS)
    for cli in (train, evaluate, diagnose, fleet, generate, validate, bench, prognose):
        keys |= {a for a, _ in _USAGE_KEY.findall(cli.USAGE) if a}
    for method, config_type in METHODS.items():
        options = set(options_of(config_type))
        keys |= options
        for prefix, name in OPTION_PREFIXES.items():
            if name == method:
                keys |= {f"{prefix}.{o}" for o in options}
    keys |= set(inspect.signature(calibrate).parameters) | set(_READER_OPTIONS)
    keys |= {"outlier_z", "misfit"}  # calibrate's options read before the method's
    for build in (Model.from_function, Model.from_step):
        keys |= set(inspect.signature(build).parameters)
    return keys


@pytest.mark.parametrize(("name", "page"), _mentions(RESULT_ATTR))
def test_every_result_attribute_the_docs_name_exists(name, page):
    if name in FILE_SUFFIXES:
        return
    assert name in _result_attributes(), f"{page}: `result.{name}` does not exist"


def test_every_option_the_docs_name_is_taken_somewhere():
    valid = _valid_keys()
    wrong = [
        f"{page}: `{key}=`"
        for key, page in _mentions(INLINE_KEY)
        if key not in valid
        and key not in NOT_KEYS
        and not key.isupper()  # environment variables (JAXCAL_CACHE=...)
        and key not in jax.config.values  # a JAX flag
    ]
    assert not wrong, "options no entry point takes:\n" + "\n".join(wrong)


def test_the_checks_can_fail():
    """A made-up attribute and a made-up key are caught."""
    assert "noise_stdd" not in _result_attributes()
    assert "noise" in _result_attributes() and "noise_source" in _result_attributes()
    valid = _valid_keys()
    assert "windw" not in valid and "ukf.window" not in valid
    assert {"window", "ukf.q", "agent.actor_lr", "runner.num_envs"} <= valid
