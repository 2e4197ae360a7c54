"""Typed, frozen configuration of the training job and its named presets.

``python -m jaxcal.train`` builds one :class:`TrainConfig` from three choices and any
number of field overrides (STYLE §2.6)::

    python -m jaxcal.train dataset=cmapss agent=lac preset=default seed=3 \
        agent.actor_lr=1e-4 runner.num_envs=32 theta=HPT_eff_mod
    python -m jaxcal.train model=my_models.py:pump data=pump.csv theta=eff,leak

* ``dataset=`` picks a :data:`DATASET_PRESETS` entry (which file, how it is read);
  ``model=`` (a ``jaxcal.models.load`` spec; ``engine=`` is an alias) with
  ``data=<file>`` trains on any model's data (the ``file`` preset, the default when
  ``model=`` or ``data=`` is given without ``dataset=``);
* ``preset=`` picks a formulation and size: ``default`` (incremental actions through
  the physics F, :mod:`jaxcal.envs.increment`: a learned feedback on the prediction
  error, the most accurate policy and the quickest to train), ``absolute`` (the
  paper's formulation, the action sets theta through the learned surrogate D, tuned
  to the 20-minute budget on a 2-core CPU), ``smoke`` (``absolute`` with tiny
  networks and two chunks; tests) and ``paper`` (``absolute`` with the paper's
  appendix hyperparameters for the agent, same budget);
* ``agent=`` picks SAC, LAC or CLAC *within* the preset (:func:`agent_presets`);
* every other ``key=value`` sets a field (dotted for nested configs); ``sensors``
  and ``theta`` are top-level fields, and :data:`TOP_LEVEL_ALIASES` lists the short
  forms (``data``/``path`` mean ``dataset.path``, ``outputs`` means ``sensors``,
  ``test_units``/``val_units`` the ``dataset.`` fields).

Existing config dataclasses are reused, not redefined: ``SurrogateConfig`` (with its
``RegressorConfig``), ``SACConfig | LACConfig | CLACConfig`` and ``RunnerConfig``. The
environment's ``EnvConfig`` needs the data's dimensions, so the run-level knobs of the
environment live in :class:`TrackingConfig` and ``EnvConfig`` is derived from it.

What the ``default`` preset changes from ``absolute``, and why (tuned on ``cmapss``
validation unit 6, never on test units; results/paper/REPORT.md, "The RL calibrator"):
``dynamics=physics``, ``env.action=increment`` (largest step half the box width),
``env.cost=log`` (a halving of the error weighs the same at every scale: with the
squared cost the policy never learned to contract the error at idle, where the
outputs barely see theta), CLAC's smoothness threshold 0.1 instead of 0.002 (a
feedback's action changes sign whenever the error does; at 0.002 the constraint held
the action near constant) and :data:`DEFAULT_CHUNKS`.

What the ``absolute`` preset changes from the paper, and why (same validation unit;
``results/train/README.md``):

* initial entropy temperature 0.01 instead of 2, with its own Adam step 1e-3 instead
  of 1e-4: the tracking costs are of order 1e-3, so an entropy bonus weighted 2
  dominates the policy loss until the temperature has decayed, which at a log-step of
  1e-4 takes most of the budget (``preset=paper`` keeps 2);
* initial Lyapunov multiplier 1 instead of 0.1 (it saturates at its clip of 1 anyway);
* actor learning rate 3e-4 instead of 1e-4; critic 3e-4 as in the paper;
* gamma = 0.9 instead of 0.99: the cost of an action is almost immediate (the policy
  sets x-hat_{t+1} and is judged at t + 1);
* CLAC smoothness threshold 0.002 instead of the reference code's 0.02 (a change of
  the squashed action in [-1, 1]; the true theta drifts far slower).

Each was a single seed on a shared machine: indications, not significant differences.
The ``paper`` preset keeps every agent value of the paper's appendix table.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

from jaxcal.agents.configs import CLACConfig, LACConfig, SACConfig
from jaxcal.nets.mlp import RegressorConfig
from jaxcal.runs.lock import check_run_name
from jaxcal.settings import parse_overrides
from jaxcal.surrogate.model import SurrogateConfig
from jaxcal.training.config_sections import (  # noqa: F401 (re-exported)
    BudgetConfig,
    DataConfig,
    OutputConfig,
    SimulationConfig,
    TrackingConfig,
    TuneConfig,
    check_choices,
)
from jaxcal.training.runner import RunnerConfig

AgentConfig = SACConfig | LACConfig | CLACConfig
AGENT_NAMES: dict[type, str] = {SACConfig: "sac", LACConfig: "lac", CLACConfig: "clac"}
PRESET_NAMES: tuple[str, ...] = ("default", "absolute", "smoke", "paper")
TOP_LEVEL_ALIASES: dict[str, str] = {
    "path": "dataset.path",
    "data": "dataset.path",
    "outputs": "sensors",
    "test_units": "dataset.test_units",
    "val_units": "dataset.val_units",
    "engine": "model",
}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """The resolved configuration of one training run (written to ``config.json``)."""

    seed: int = 0  # root PRNG seed (surrogate fit, agent, environments)
    # the physics model (jaxcal.models.load spec: name, module:attr, file.py:attr);
    # "": the engine an N-CMAPSS file names (cmapss for NASA's files)
    model: str = ""
    # transition of the tracking MDP: the learned surrogate D (paper) or the physics F
    dynamics: Literal["surrogate", "physics"] = "surrogate"
    preset: str = "default"  # the preset the config was built from (informational)
    dataset: DataConfig = DataConfig()
    sensors: tuple[str, ...] = ()  # observed sensors; (): the data set's default
    theta: tuple[str, ...] = ()  # declared parameters; (): those varying in dev T
    # output noise std, one per used output or name:std pairs; (): estimated when a
    # simulation needs it (a UKF pass over the training units)
    noise: tuple[str, ...] = ()
    surrogate: SurrogateConfig = SurrogateConfig()
    agent: AgentConfig = CLACConfig()
    runner: RunnerConfig = RunnerConfig()
    env: TrackingConfig = TrackingConfig()
    budget: BudgetConfig = BudgetConfig()
    simulate: SimulationConfig = SimulationConfig()
    tune: TuneConfig = TuneConfig()
    output: OutputConfig = OutputConfig()

    def __post_init__(self) -> None:
        check_choices(self, "")
        if type(self.agent) not in AGENT_NAMES:
            raise ValueError(
                f"agent must be one of {[c.__name__ for c in AGENT_NAMES]}, got "
                f"{type(self.agent).__name__}"
            )
        # confined to runs_dir: refused here, before any file is read or written
        check_run_name(
            self.run_name,
            "name"
            if self.output.name
            else "name (derived from the data's name; set name=)",
        )

    @property
    def agent_name(self) -> str:
        """``sac``, ``lac`` or ``clac``."""
        return AGENT_NAMES[type(self.agent)]

    @property
    def run_name(self) -> str:
        """The run folder name (``output.name`` or one derived from the choices)."""
        if self.output.name:
            return self.output.name
        data = self.dataset.name or Path(self.dataset.path).stem or "data"
        dynamics = self.dynamics + ("-inc" if self.env.action == "increment" else "")
        name = f"{data}-{self.agent_name}-{dynamics}-s{self.seed}"
        return name if self.preset == "default" else f"{name}-{self.preset}"


# ----------------------------------------------------------------------- presets

DATASET_PRESETS: dict[str, DataConfig] = {
    # Dataset #1 (paper Table 1): ten run-to-failure units, HPT efficiency degrading.
    "cmapss": DataConfig(),
    # Dataset #2: 1,296 fault scenarios of four turbine modifiers at 1 Hz; every 5th
    # row keeps the 5,000 s flights at 1,000 steps so a run fits the budget.
    "agtf30": DataConfig(
        name="agtf30", path="data/agtf30.h5", generate="agtf30", stride=5
    ),
    # A user's N-CMAPSS file (NASA's DS01-DS08 or one of ours): path= is required;
    # NASA's 1 Hz rows are read every 10 s.
    "ncmapss": DataConfig(name="ncmapss", path="", generate="", stride=10),
    # The generator's tiny fleet (three short units), for quick end-to-end checks.
    "tiny": DataConfig(name="tiny", path="data/tiny.h5", generate="tiny"),
    # Any model's data file (data=<file>, model=<spec>): read as it is.
    "file": DataConfig(name="", path="", generate=""),
}

# budget.target_theta_rmse per dataset preset: Dataset #1's accuracy goal (the
# paper's CLAC reached 3.30e-4 in 6,200 s); other presets have none yet.
TARGET_THETA_RMSE: dict[str, float] = {"cmapss": 2.5e-4}

# the default preset's chunks per dataset preset (others: 40): Dataset #1's
# validation tracking is lowest at chunk 35 of 40 (results/train/make_train_time.md)
DEFAULT_CHUNKS: dict[str, int] = {"cmapss": 35}

# the default preset on any model's data (_any_model_defaults)
ANY_MODEL_CHUNKS = 6
# simulated copies of each training unit: with one copy the policy learnt the
# copies' theta paths, not the feedback
ANY_MODEL_COPIES = 16
# the deployed network's widths on any model: a 256-wide actor's step costs more
# than a small model's whole UKF step (results/bench/deploy.json)
ANY_MODEL_ACTOR = (64, 64)
# the samples the filter step's noise is averaged over on any model
# (env.filter_adapt): a biased or drifting sensor is weighed less where spare
# outputs show it (results/policy_robust)
ANY_MODEL_FILTER_ADAPT = 32
# the kept actor tuned by gradient through the filter on simulated units' theta
# error (tune.steps), kept where the selection units agree and no guard set loses
# (clean, drawn across the box, with effects); the actor-critic stops after
# ANY_MODEL_PATIENCE scorings that do not beat its start
# (results/policy_any_model/issue41.md)
ANY_MODEL_TUNE_STEPS = 400
ANY_MODEL_PATIENCE = 2
# Tuned on clean units alone, the actor lost what the filter held under a fault on
# one output the guard's mix rarely drew; tuned on effects alone, it learnt to sit
# still under a drift. So half the tuning units carry an effect and the score
# weighs them half (tune.effects), the clean selection units stay within 5 % of the
# start and the units drawn across the box within 1.5x (results/policy_robust/robust)
ANY_MODEL_TUNE_EFFECTS = 0.5
ANY_MODEL_CLEAN_LIMIT = 1.05
ANY_MODEL_BOX_TOLERANCE = 0.5
# the tuning fits output-bias states in the filter beside the actor (tune.bias,
# jaxcal.envs.bias_states): a sensor bias is estimated, not read as theta
# (results/policy_robust/bias)
ANY_MODEL_TUNE_BIAS = True

_TUNED_AGENT = dict(
    actor_lr=3e-4,
    initial_entropy_temperature=0.01,
    entropy_temperature_lr=1e-3,
    gamma=0.9,
)
_TUNED_LYAPUNOV = dict(initial_lyapunov_multiplier=1.0)
_TUNED_SMOOTHNESS = dict(smoothness_threshold=0.002)
# a feedback policy's action changes sign with the error (module docstring)
_FEEDBACK_SMOOTHNESS = dict(smoothness_threshold=0.1)
_SMOKE_NETS = dict(actor_hidden_sizes=(32, 32), critic_hidden_sizes=(32, 32))


def agent_presets(preset: str) -> dict[str, AgentConfig]:
    """The ``agent=`` registry of a preset: ``{"sac", "lac", "clac"}`` configs.

    Raises:
        ValueError: unknown preset.
    """
    if preset == "paper":
        return {"sac": SACConfig(), "lac": LACConfig(), "clac": CLACConfig()}
    if preset not in PRESET_NAMES:
        raise ValueError(f"unknown preset {preset!r}; choose one of {PRESET_NAMES}")
    extra = _SMOKE_NETS if preset == "smoke" else {}
    smooth = _FEEDBACK_SMOOTHNESS if preset == "default" else _TUNED_SMOOTHNESS
    return {
        "sac": SACConfig(**_TUNED_AGENT, **extra),
        "lac": LACConfig(**_TUNED_AGENT, **_TUNED_LYAPUNOV, **extra),
        "clac": CLACConfig(**_TUNED_AGENT, **_TUNED_LYAPUNOV, **smooth, **extra),
    }


_DEFAULT_SURROGATE = SurrogateConfig(
    fit=RegressorConfig(
        learning_rate=1e-3,
        batch_size=256,
        num_epochs=40,
        validation_fraction=0.1,
        patience=10,
    )
)
_DEFAULT_RUNNER = RunnerConfig(
    num_envs=16,
    num_steps_per_chunk=1000,
    updates_per_step=1,
    batch_size=256,
    buffer_size=500_000,
    warmup_steps=10_000,
    min_buffer_size=10_000,
)


def make_train_config(dataset: str = "cmapss", preset: str = "default") -> TrainConfig:
    """The base config of a (dataset, preset) pair, before field overrides.

    Raises:
        ValueError: unknown dataset or preset (the message lists the choices).
    """
    if dataset not in DATASET_PRESETS:
        raise ValueError(
            f"unknown dataset {dataset!r}; choose one of {', '.join(DATASET_PRESETS)}"
        )
    agents = agent_presets(preset)
    cfg = TrainConfig(
        preset=preset,
        dataset=DATASET_PRESETS[dataset],
        surrogate=_DEFAULT_SURROGATE,
        agent=agents["clac"],
        runner=_DEFAULT_RUNNER,
    )
    if preset == "default":
        cfg = dataclasses.replace(
            cfg,
            dynamics="physics",
            env=TrackingConfig(action="increment", cost="log"),
            budget=BudgetConfig(num_chunks=DEFAULT_CHUNKS.get(dataset, 40)),
        )
    if preset == "smoke":
        cfg = dataclasses.replace(
            cfg,
            surrogate=SurrogateConfig(
                hidden_sizes=(32, 32),
                fit=RegressorConfig(learning_rate=3e-3, batch_size=256, num_epochs=2),
            ),
            runner=RunnerConfig(
                num_envs=4,
                num_steps_per_chunk=25,
                batch_size=32,
                buffer_size=2_000,
                warmup_steps=100,
                min_buffer_size=100,
            ),
            env=TrackingConfig(episode_length=10),
            budget=BudgetConfig(
                num_chunks=2, eval_every=1, ckpt_every=1, time_limit_s=None
            ),
            # the generated 1 Hz files are thinned; a user's file is read as it is
            dataset=cfg.dataset
            if dataset == "file"
            else dataclasses.replace(cfg.dataset, stride=max(cfg.dataset.stride, 20)),
        )
    if dataset == "file":
        cfg = _any_model_defaults(cfg, preset)
    target = TARGET_THETA_RMSE.get(dataset)
    return dataclasses.replace(
        cfg, budget=dataclasses.replace(cfg.budget, target_theta_rmse=target)
    )


def _any_model_defaults(cfg: TrainConfig, preset: str) -> TrainConfig:
    """The ``default`` preset on any model's data (the ``file`` preset): the labels
    only score and the model makes the labelled units the run needs
    (:mod:`jaxcal.training.data.simulated`).

    The box is the model's bounds and a deployed policy starts from the model's
    nominal values, as the UKF does. The policy trains on the training units and on
    simulated copies of them, the copies' log cost on their noise-free outputs with
    its floor at the noise (the data alone stop rewarding precision at the noise; the
    copies alone lose what the data teach under model error), for
    :data:`ANY_MODEL_CHUNKS` chunks scored after each; the kept one has the lowest
    theta RMSE on simulated validation units, and its band is fitted on simulated
    units, both along the theta drifts the UKF finds in the data
    (``simulate.paths=data``). The policy observes an extended Kalman filter's step on
    theta (and, where the outputs determine theta, the residual's Gauss-Newton step)
    and the stream's age, and its untrained action is the filter's step whole
    (``env.gauss_newton=filter``, ``env.filter_gain=1``, ``env.filter_whole``;
    ``results/policy_any_model/README.md``); its actor is :data:`ANY_MODEL_ACTOR`
    wide, and its filter weighs each output by the noise its innovations show
    (``env.filter_adapt``). The actor-critic stops after :data:`ANY_MODEL_PATIENCE`
    scorings without a better policy, and the kept actor is then tuned by gradient
    through the filter (``tune``) on units half of which carry an undeclared effect,
    with the filter's output-bias states fitted beside it. The other
    presets keep their formulation; without labels they fit D and the band on
    simulated units as well.
    """
    if preset != "default":
        return cfg
    return dataclasses.replace(
        cfg,
        dataset=dataclasses.replace(cfg.dataset, labels="score"),
        agent=dataclasses.replace(cfg.agent, actor_hidden_sizes=ANY_MODEL_ACTOR),
        env=dataclasses.replace(
            cfg.env,
            start="prior",
            gauss_newton="filter",
            filter_whole=True,
            filter_adapt=ANY_MODEL_FILTER_ADAPT,
        ),  # fmt: skip
        simulate=SimulationConfig(
            train="both",
            band="simulated",
            cost_floor="noise",
            copies=ANY_MODEL_COPIES,
            paths="data",
        ),
        tune=dataclasses.replace(
            cfg.tune,
            steps=ANY_MODEL_TUNE_STEPS,
            effects=ANY_MODEL_TUNE_EFFECTS,
            clean_limit=ANY_MODEL_CLEAN_LIMIT,
            clean_tolerance=ANY_MODEL_BOX_TOLERANCE,
            bias=ANY_MODEL_TUNE_BIAS,
        ),
        budget=dataclasses.replace(
            cfg.budget,
            select="sim_theta",
            num_chunks=ANY_MODEL_CHUNKS,
            patience=ANY_MODEL_PATIENCE,
            eval_every=1,
            ckpt_every=1,
        ),
    )


def resolve_config(argv: Sequence[str]) -> TrainConfig:
    """The :class:`TrainConfig` of a ``key=value`` command line.

    ``preset`` and ``dataset`` pick the base (:func:`make_train_config`; without
    ``dataset=``, ``model=``/``data=`` pick the ``file`` preset, else ``cmapss``),
    ``agent`` picks from :func:`agent_presets` of that preset, the
    :data:`TOP_LEVEL_ALIASES` are expanded; everything else goes through
    :func:`jaxcal.settings.parse_overrides`.

    Raises:
        ValueError: malformed token, unknown key (the message lists the valid keys),
            unknown preset, or a badly typed value.
    """
    choices: dict[str, str] = {}
    rest: list[str] = []
    for token in argv:
        key, sep, value = token.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"malformed argument {token!r}: expected key=value")
        if key in ("preset", "dataset"):
            if key in choices:
                raise ValueError(f"key {key!r} given twice")
            choices[key] = value.strip()
        else:
            rest.append(f"{TOP_LEVEL_ALIASES.get(key, key)}={value}")
    preset = choices.get("preset", "default")
    if preset not in PRESET_NAMES:
        raise ValueError(f"unknown preset {preset!r}; choose one of {PRESET_NAMES}")
    keys = {t.partition("=")[0].strip() for t in argv}
    default = "file" if keys & {"model", "engine", "data"} else "cmapss"
    base = make_train_config(choices.get("dataset", default), preset)
    try:
        return parse_overrides(rest, base, {"agent": agent_presets(preset)})
    except ValueError as err:
        raise ValueError(
            f"{err} (also: preset={'|'.join(PRESET_NAMES)}, "
            f"dataset={'|'.join(DATASET_PRESETS)}, model=<name|module:attr|file.py:"
            "attr>, data=<file>, outputs=<names>)"
        ) from None
