"""Tests for the key=value override parser and the config JSON round trip."""

from __future__ import annotations

import dataclasses
import json
from typing import Literal

import pytest

from jaxcal.settings import coerce, config_from_dict, config_to_dict, parse_overrides


@dataclasses.dataclass(frozen=True)
class SACConfig:
    actor_lr: float = 1e-4  # policy learning rate
    hidden_sizes: tuple[int, ...] = (256, 256)


@dataclasses.dataclass(frozen=True)
class LACConfig:
    actor_lr: float = 1e-4
    alpha3: float = 1.0
    hidden_sizes: tuple[int, ...] = (256, 256)


@dataclasses.dataclass(frozen=True)
class DataConfig:
    name: str = "cmapss"
    num_units: int = 10
    subsample: int | None = None


@dataclasses.dataclass(frozen=True)
class RootConfig:
    seed: int = 0
    x64: bool = False
    out: str = "data/out.h5"
    theta: tuple[str, ...] = ("HPT_eff_mod",)
    dynamics: Literal["surrogate", "physics"] = "surrogate"
    dataset: DataConfig = DataConfig()
    agent: SACConfig | LACConfig = SACConfig()


AGENTS = {"sac": SACConfig(), "lac": LACConfig(alpha3=2.0)}
DATASETS = {"cmapss": DataConfig(), "agtf30": DataConfig(name="agtf30", num_units=3)}
GROUPS = {"agent": AGENTS, "dataset": DATASETS}


def test_group_preset_and_dotted_override_in_any_order():
    cfg = parse_overrides(["agent.actor_lr=3e-4", "agent=lac"], RootConfig(), GROUPS)
    assert cfg.agent == LACConfig(actor_lr=3e-4, alpha3=2.0)
    cfg = parse_overrides(
        ["dataset=agtf30", "dataset.num_units=7"], RootConfig(), GROUPS
    )
    assert cfg.dataset == DataConfig(name="agtf30", num_units=7)


def test_values_are_coerced_to_annotated_types():
    argv = [
        "seed=3",
        "x64=true",
        "out=data/x.h5",
        "theta=HPC_eff_mod, HPC_flow_mod",
        "dynamics=physics",
        "dataset.subsample=10",
        "agent.hidden_sizes=64,32",
    ]
    cfg = parse_overrides(argv, RootConfig(), GROUPS)
    assert cfg.seed == 3 and cfg.x64 is True and cfg.out == "data/x.h5"
    assert cfg.theta == ("HPC_eff_mod", "HPC_flow_mod")
    assert cfg.dynamics == "physics"
    assert cfg.dataset.subsample == 10
    assert cfg.agent.hidden_sizes == (64, 32)
    cfg = parse_overrides(["dataset.subsample=none", "seed=1e3"], cfg, GROUPS)
    assert cfg.dataset.subsample is None and cfg.seed == 1000


def test_base_config_is_not_mutated():
    base = RootConfig()
    parse_overrides(["seed=5", "agent=lac"], base, GROUPS)
    assert base == RootConfig()


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["sed=3"], "valid keys"),
        (["agent.actor_rl=1"], "actor_lr"),
        (["agent=ppo"], "choose one of: sac, lac"),
        (["seed"], "expected key=value"),
        (["=3"], "expected key=value"),
        (["seed=three"], "seed='three': expected an integer"),
        (["x64=maybe"], "expected a bool"),
        (["agent.actor_lr=nan"], "NaN"),
        (["dynamics=both"], "surrogate, physics"),
        (["dataset=cmapss", "dataset=agtf30"], "given twice"),
        (["dataset=foo"], "choose one of"),
        (["seed.x=1"], "not a config"),
    ],
)
def test_bad_arguments_raise_clear_value_errors(argv, fragment):
    with pytest.raises(ValueError) as info:
        parse_overrides(argv, RootConfig(), GROUPS)
    assert fragment in str(info.value)


def test_unknown_key_message_lists_every_valid_key():
    with pytest.raises(ValueError) as info:
        parse_overrides(["dataset.units=3"], RootConfig(), GROUPS)
    message = str(info.value)
    assert "'dataset.units'" in message
    for name in ("name", "num_units", "subsample"):
        assert name in message


def test_nested_config_without_preset_needs_dotted_keys():
    with pytest.raises(ValueError, match="dataset.<field>"):
        parse_overrides(["dataset=agtf30"], RootConfig(), {})


def test_coerce_fixed_length_tuple_checks_length():
    assert coerce("1,2.5", tuple[int, float], "pair") == (1, 2.5)
    with pytest.raises(ValueError, match="2 comma-separated"):
        coerce("1,2,3", tuple[int, float], "pair")
    assert coerce("", tuple[str, ...], "theta") == ()


def test_config_json_round_trip_keeps_union_member_and_tuples():
    cfg = parse_overrides(
        ["agent=lac", "theta=a,b", "dataset.subsample=4"], RootConfig(), GROUPS
    )
    data = json.loads(json.dumps(config_to_dict(cfg)))
    assert data["agent"]["_type"] == "LACConfig"
    back = config_from_dict(RootConfig, data)
    assert back == cfg
    assert isinstance(back.theta, tuple) and isinstance(back.agent, LACConfig)


def test_config_from_dict_rejects_unknown_fields_and_wrong_type():
    with pytest.raises(ValueError, match="unknown fields"):
        config_from_dict(DataConfig, {"name": "x", "colour": 1})
    with pytest.raises(ValueError, match="expected 'DataConfig'"):
        config_from_dict(DataConfig, {"_type": "SACConfig"})
    assert config_from_dict(DataConfig, {"num_units": 4}) == DataConfig(num_units=4)


def test_real_nested_configs_parse_and_round_trip():
    from jaxcal.calibrators.methods.e2e.network import E2EConfig
    from jaxcal.surrogate.model import SurrogateConfig

    cfg = parse_overrides(
        ["hidden_sizes=64,64", "fit.learning_rate=3e-4", "fit.patience=none"],
        SurrogateConfig(),
    )
    assert cfg.hidden_sizes == (64, 64) and cfg.fit.learning_rate == 3e-4
    assert cfg.fit.patience is None and cfg.fit.batch_size == 256
    assert config_from_dict(SurrogateConfig, config_to_dict(cfg)) == cfg
    with pytest.raises(ValueError, match="validation_fraction must be in"):
        parse_overrides(["fit.validation_fraction=1.5"], E2EConfig())


def test_every_command_line_has_the_one_grammar_with_its_documented_flags():
    # the flag spellings of the docs and the Makefile are key=value tokens of the
    # one parser (jaxcal.settings.parse_overrides): both forms give the same config
    from jaxcal.cli import bench, validate
    from jaxcal.cli.args import flags_as_overrides
    from jaxcal.cli.fleet import parse_args as fleet_args

    flags = {"--engine": "engine", "--out": "out", "--quick": "quick"}
    assert flags_as_overrides(
        ["--engine", "agtf30", "--out=r.json", "--quick", "seed=1"],
        flags,
        switches=("--quick",),
    ) == ["engine=agtf30", "out=r.json", "quick=true", "seed=1"]
    with pytest.raises(ValueError, match="unknown flag '--engin'.*--engine"):
        flags_as_overrides(["--engin", "x"], flags)
    with pytest.raises(ValueError, match="--out needs a value"):
        flags_as_overrides(["--out"], flags)

    want = validate.ValidateArgs(engine="agtf30", out=None, quick=True)
    assert validate.parse_args(["--engine", "agtf30", "--quick"]) == want
    assert validate.parse_args(["engine=agtf30", "quick=true"]) == want
    with pytest.raises(ValueError, match="engine='x'.*cmapss, agtf30"):
        validate.parse_args(["engine=x"])

    want = bench.BenchArgs(engine="cmapss", batch=8, repeats=2, out="b.json")
    argv = ["engine", "--batch", "8", "--repeats=2", "--out", "b.json"]
    assert bench.parse_args(argv) == want
    assert bench.parse_args(["engine", "batch=8", "repeats=2", "out=b.json"]) == want
    with pytest.raises(ValueError, match="say what to bench"):
        bench.parse_args(["--batch", "8"])
    with pytest.raises(ValueError, match="positive"):
        bench.parse_args(["engine", "batch=0"])
    assert bench.main(["engine", "--batches", "8"]) == 2  # a typo: usage, exit 2

    base = ["data=a.csv", "out=o.h5"]
    flagged = fleet_args([*base, "--coordinator", "h:1", "--num-processes=2",
                          "--process-id", "0"])  # fmt: skip
    keyed = fleet_args([*base, "coordinator=h:1", "num_processes=2", "process_id=0"])
    assert flagged == keyed and keyed[1]["num_processes"] == 2
