"""Presets of ``experiments/paper.py``: which data, trainings and evaluations it runs.

``full`` reproduces the paper at the sizes of ``python -m jaxcal.generate`` and
``python -m jaxcal.train`` (their files in ``data/`` and ``runs/`` are reused);
``quick`` runs the same steps on tiny generated data with smoke trainings, short test
trajectories and without the methods whose compilation alone takes minutes, so that
the whole pipeline is exercised in a few minutes (a test runs it).
"""

from __future__ import annotations

import dataclasses

from jaxcal.calibrators.methods.e2e.network import E2EConfig
from jaxcal.nets.mlp import RegressorConfig
from jaxcal.paper.npe import NPEConfig
from jaxcal.paper.suite import SuiteConfig
from jaxcal.paper.tables import ON_MODEL, POLICIES

# CLAC-F: the CLAC policy trained and deployed on the physics F instead of the
# surrogate D (dynamics=physics), which isolates what D's model error costs;
# CLAC-inc: the formulation, incremental actions deployed through F
# ON_MODEL: every registered method on the model beside the UKF (least squares, ...)
ALL_METHODS = (
    "UKF", *ON_MODEL, "E2E", "E2E-sim", "CLAC", "LAC", "SAC", "CLAC-F", "CLAC-inc",
    "CLAC-gate",
)  # fmt: skip
# CLAC-gate trains nothing: CLAC-inc gated by CLAC where F misfits the data
# (jaxcal.paper.gate_steps), fitted on the validation units by fit-ds1-CLAC-gate
# Policies trained through `python -m jaxcal.train`: agent key (the step name
# train-<data set>-<key>) -> (method name, the training overrides that make it).
# The paper's formulation (absolute actions) trains with the CLI's `absolute` preset,
# CLAC-inc with its `default` one (incremental actions through F); a preset of its
# own (the quick run's smoke) gets FEEDBACK for CLAC-inc instead.
AGENTS = {
    "clac": ("CLAC", ("agent=clac",)),
    "lac": ("LAC", ("agent=lac",)),
    "sac": ("SAC", ("agent=sac",)),
    "clac-f": ("CLAC-F", ("agent=clac", "dynamics=physics")),
    "clac-inc": ("CLAC-inc", ("agent=clac",)),
}  # fmt: skip
FEEDBACK = (
    "dynamics=physics", "env.action=increment", "env.cost=log",
    "agent.smoothness_threshold=0.1",
)  # fmt: skip
# the "best policy" configuration, whose numbers the report's summary shows
BEST_POLICY = "CLAC-gate"
# (data set, variant, methods): the paper's tables and our extra columns
EVALUATIONS = (
    ("ds1", "clean", ALL_METHODS),
    ("ds1", "bias", ("UKF", *POLICIES, "CLAC-gate")),
    ("ds1", "noise", ("UKF", *POLICIES, "CLAC-gate")),
    ("ds1", "snr70", ("UKF", "E2E", "E2E-sim", *POLICIES, "CLAC-gate")),
    ("ds2", "clean", ("UKF", *ON_MODEL, "E2E", "E2E-sim", "CLAC")),
    ("ds2-d1", "clean", ("UKF", "CLAC")),
    ("ds2-d2", "clean", ("UKF", "CLAC")),
)
# the paper's robustness settings (§5): F x alpha, F + N(0, alpha_eta), SNR 70 dB
VARIANTS = {"clean": (1.0, 0.0), "bias": (1.02, 0.0), "noise": (1.0, 0.1)}
# factorial levels of the scalability variants of Dataset #2 (the d = 4 set has 6)
LEVELS_D1 = ",".join(f"{-0.001 * i + 0.0:g}" for i in range(21))
LEVELS_D2 = ",".join(f"{-0.002 * i + 0.0:g}" for i in range(11))


# Seconds per step on the shared 2-core CPU (the longest matching prefix applies),
# from the training job's README (runs), the engine benchmark (data) and probes of the
# UKF and least squares, which take about 3 and 6 minutes to compile cold (the UKF then
# runs ~3 ms per step of the 4 test units of Dataset #1, least squares ~10 ms).
# fmt: off
FULL_ESTIMATES = {
    "data-ds1": 150, "data-ds1-snr70": 120, "data-ds2": 900, "data-ds2-d1": 90,
    "data-ds2-d2": 150,
    "train-ds1-clac": 1650, "train-ds1-lac": 2100, "train-ds1-sac": 2300,
    "train-ds1-clac-f": 2700, "eval-ds1-CLAC-F": 120, "latency-ds1-CLAC-F": 60,
    "train-ds1-clac-inc": 2700, "eval-ds1-CLAC-inc": 120, "latency-ds1-CLAC-inc": 60,
    "fit-ds1-CLAC-gate": 90, "eval-ds1-CLAC-gate": 150, "latency-ds1-CLAC-gate": 60,
    "train-ds2-clac": 1900, "train-ds2-d": 1500, "ident-ds2": 90,
    "check": 30,
    "fit-ds1-E2E": 180, "fit-ds1-E2E-sim": 240, "fit-ds2-E2E": 240,
    "fit-ds2-E2E-sim": 300,
    "eval-ds1-UKF-clean": 420, "eval-ds1-UKF": 200, "eval-ds1-LS": 720,
    "eval-ds1-E2E": 30, "eval-ds1": 15, "eval-ds2-UKF": 270, "eval-ds2-LS": 540,
    "eval-ds2-E2E": 30, "eval-ds2": 20, "eval-ds2-d1-UKF": 240, "eval-ds2-d2-UKF": 240,
    "eval-ds2-d": 20,
    "latency-ds1-UKF": 90, "latency-ds1-LS": 240, "latency": 10, "figures": 30,
    "fit-ds1-NPE": 150, "eval-ds1-NPE": 300, "latency-ds1-NPE": 10,
    "calib-ds1-UKF": 660,  # the UKF over the validation and again the test units
}
QUICK_ESTIMATES = {
    "data": 5, "train": 6, "check": 1, "fit": 2, "eval": 1, "eval-ds1-UKF-clean": 30,
    "latency": 1, "latency-ds1-UKF": 7, "figures": 5,
    # a smoke training on F compiles the engine inside the environment (~1 min)
    "train-ds1-clac-inc": 70, "eval-ds1-CLAC-inc": 15, "latency-ds1-CLAC-inc": 5,
    "fit-ds1-CLAC-gate": 20, "eval-ds1-CLAC-gate": 15, "latency-ds1-CLAC-gate": 5,
    "calib-ds1-UKF": 1,  # the eval step's compiled UKF, same shapes
}
# fmt: on


@dataclasses.dataclass(frozen=True)
class DataSpec:
    """A data file: generator preset, field overrides, file name, training preset."""

    generator: str
    overrides: tuple[str, ...] = ()
    file: str = ""
    train_dataset: str = "cmapss"


@dataclasses.dataclass(frozen=True)
class Preset:
    """Everything a run of this script does (``full`` and ``quick`` below)."""

    name: str
    datasets: dict  # key -> DataSpec: ds1, ds1-snr70, ds2, ds2-d1, ds2-d2
    suites: dict  # key -> SuiteConfig of ds1, ds2, ds2-d1, ds2-d2
    train_args: dict  # dataset key -> extra training overrides
    scalability: tuple[str, ...]  # Dataset #2 variants of the d study (besides d = 4)
    skip: tuple[tuple[str, str], ...]  # (data set, method) pairs left out
    latency_repeats: int
    estimates: dict  # step name prefix -> seconds on the reference machine
    in_out: bool  # data and runs live under <out> (quick) or in data/, runs/ (full)
    description: str  # what the numbers of this preset mean (top of the report)
    # data sets whose weakest theta direction is analysed (jacfwd of F: compiling it
    # takes minutes, like least squares, so not in the smoke run)
    identifiability: tuple[str, ...] = ()


FULL = Preset(
    name="full",
    datasets={
        "ds1": DataSpec("cmapss", (), "cmapss.h5", "cmapss"),
        "ds1-snr70": DataSpec("cmapss", ("sensor_snr_db=70",), "cmapss-snr70.h5"),
        "ds2": DataSpec("agtf30", (), "agtf30.h5", "agtf30"),
        "ds2-d1": DataSpec(
            "agtf30",
            ("degrading=HPT_eff_mod", f"fault_levels={LEVELS_D1}"),
            "agtf30-d1.h5",
            "agtf30",
        ),
        "ds2-d2": DataSpec(
            "agtf30",
            ("degrading=HPT_eff_mod,HPT_flow_mod", f"fault_levels={LEVELS_D2}"),
            "agtf30-d2.h5",
            "agtf30",
        ),
    },
    suites={
        "ds1": SuiteConfig(e2e_units=(1, 4, 7, 9)),
        # a seeded subset of the 259 test scenarios, the same for every method:
        # least squares on all of them alone would take ~10 more minutes
        "ds2": SuiteConfig(max_test_units=100),
        "ds2-d1": SuiteConfig(),
        "ds2-d2": SuiteConfig(),
    },
    # every policy gets its full 150 chunks, whatever the wall clock: the training
    # job's 1,080 s guard would stop them at 60-90 chunks on this shared CPU, and the
    # scalability study needs equal budgets for d = 1, 2, 4
    train_args={
        key: ("budget.time_limit_s=none",) for key in ("ds1", "ds2", "ds2-d1", "ds2-d2")
    },
    scalability=("ds2-d1", "ds2-d2"),
    skip=(),
    latency_repeats=300,
    estimates=FULL_ESTIMATES,
    in_out=False,
    description="Full sizes: Dataset #1 and #2 as generated by `python -m "
    "jaxcal.generate`; the paper's policies (CLAC, LAC, SAC, CLAC-F) from the training "
    "job's `absolute` preset run to its 150 chunks, CLAC-inc from its `default` preset "
    "(35 chunks on Dataset #1, 40 on #2; `budget.time_limit_s=none` for both).",
    identifiability=("ds2",),
)

_QUICK_E2E = E2EConfig(
    fit=RegressorConfig(learning_rate=1e-3, batch_size=64, num_epochs=3)
)
# a few seconds: a two-transform MAF, three epochs, 50 posterior draws
_QUICK_NPE = NPEConfig(
    hidden_features=16, num_transforms=2, max_samples=2000, batch_size=256,
    max_epochs=3, num_posterior_samples=50,
)  # fmt: skip
# Dataset #2's role in the smoke run: a tiny fault-scenario set of the cmapss engine, so
# that generation and F share the compiled engine of Dataset #1 (an agtf30 engine and a
# four-parameter UKF would add about a minute of tracing alone).
_TURBINE = "degrading=HPT_eff_mod,HPT_flow_mod,LPT_eff_mod,LPT_flow_mod"
_QUICK_SCENARIOS = ("kind=scenarios", "flight_steps=60")
QUICK = Preset(
    name="quick",
    datasets={
        "ds1": DataSpec("tiny", (), "tiny.h5", "tiny"),
        "ds1-snr70": DataSpec("tiny", ("sensor_snr_db=70",), "tiny-snr70.h5"),
        "ds2": DataSpec(
            "tiny",
            (*_QUICK_SCENARIOS, _TURBINE, "num_scenarios=10"),
            "tiny-scenarios.h5",
            "tiny",
        ),
        "ds2-d1": DataSpec(
            "tiny",
            (
                *_QUICK_SCENARIOS,
                "degrading=HPT_eff_mod",
                "num_scenarios=none",
                "fault_levels=0,-0.007,-0.014,-0.02",
            ),
            "tiny-scenarios-d1.h5",
            "tiny",
        ),
    },  # fmt: skip
    suites={
        "ds1": SuiteConfig(
            max_steps=40,
            e2e=_QUICK_E2E,
            e2e_units=(1, 2),
            e2e_max_samples=2000,
            npe=_QUICK_NPE,
        ),
        "ds2": SuiteConfig(max_steps=20, e2e=_QUICK_E2E, e2e_max_samples=2000),
        "ds2-d1": SuiteConfig(max_steps=20),
    },
    train_args={
        "ds1": ("preset=smoke", "dataset.stride=2"),
        "ds2": ("preset=smoke", "dataset.stride=3"),
        "ds2-d1": ("preset=smoke", "dataset.stride=3"),
    },
    scalability=("ds2-d1",),
    # tracing and compiling F inside least squares (or a policy's environment)
    # takes minutes, and a UKF of another parameter count another ~30 s: not in a
    # smoke run
    skip=(
        # every method on the model beside the UKF (least squares compiles for
        # minutes, the EKF ~1 min a data set): the full preset runs them
        *((ds, m) for m in ON_MODEL for ds in ("ds1", "ds2")),
        ("ds2", "UKF"),
        ("ds2-d1", "UKF"),
        ("ds1", "CLAC-F"),
    ),  # fmt: skip
    latency_repeats=20,
    estimates=QUICK_ESTIMATES,
    in_out=True,
    description="**Smoke run, not results**: tiny data, two-chunk trainings and short "
    "test trajectories; Dataset #2's role is played by a tiny fault-scenario set of "
    "the cmapss engine, and the methods on the model beside the UKF (least squares, "
    "the EKF) and the four-parameter UKF are left out. "
    "It checks the pipeline, its numbers mean nothing.",
)
PRESETS = {"full": FULL, "quick": QUICK}
