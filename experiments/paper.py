"""Reproduce every table and figure of the paper, from data generation to the report.

Usage (from the repository root)::

    python experiments/paper.py [preset=full|quick] [out=results/paper] [seed=0]
        [skip=LS,SAC]           # leave methods out (shorter; "–" in the report)
        [skip=CLAC-inc]         # e.g. where the training CLI has no env.action
    make paper                  # preset=full, out=results/paper
    make paper PRESET=quick     # 1.5 minutes with a warm cache, results/paper-quick

Steps (design/calibration.md, "The paper's results", items 1-7), each resumable — it
writes ``<out>/steps/<name>.json`` and is skipped when that file exists:

1. data sets: Dataset #1 (``cmapss``), its 70 dB sensor-noise copy, Dataset #2
   (``agtf30``, d = 4) and the d = 1 / d = 2 variants of the scalability study;
2. trainings through the training CLI with deterministic run names (CLAC, LAC, SAC,
   CLAC-F and CLAC-inc on Dataset #1; CLAC on each Dataset #2 variant); existing runs
   are reused;
3. E2E on labelled units (Dataset #1: units 1, 4, 7, 9 as in the paper) and E2E-sim
   on simulated labels; on Dataset #1 the NPE peer (``sbi``, an optional extra) on
   E2E-sim's simulations;
4. every method over whole test trajectories: clean, model bias x 1.02, model noise
   N(0, 0.1), 70 dB sensor noise; the scalability runs; single-stream latency;
   on Dataset #2, each method's error along the direction the sensors barely see;
   the UKF's std rescaled on Dataset #1's validation units (``calib-ds1-UKF``);
5. figures (PNG), ``<out>/REPORT.md`` and ``<out>/results.json`` (the step results
   plus the issue's summary against its goals, :mod:`jaxcal.paper.summary`),
   rewritten on every run.

The ``full`` preset reuses ``data/*.h5`` and ``runs/*`` (the files ``python -m
jaxcal.generate`` and ``python -m jaxcal.train dataset=cmapss agent=clac`` write); the
``quick`` preset runs the same code on tiny data with smoke trainings and writes
everything, data and runs included, under its ``out`` folder.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the presets beside us

from paper_figures import make_figures, save_traces  # noqa: E402
from paper_presets import (  # noqa: E402
    AGENTS,
    ALL_METHODS,
    EVALUATIONS,
    FEEDBACK,
    PRESETS,
    VARIANTS,
    Preset,
)

from jaxcal.paper.tables import ON_MODEL  # noqa: E402

# ----------------------------------------------------------------------- plan


@dataclasses.dataclass(frozen=True)
class Step:
    """One resumable step: name, expected seconds, printed config, the work."""

    name: str
    estimate_s: float
    config: dict
    work: Callable[[], dict]


class Context:
    """Paths, run names and the lazily built suites of one experiment."""

    def __init__(self, preset: Preset, out: Path, seed: int):
        self.preset, self.out, self.seed = preset, out, seed
        self._suites: dict = {}

    def data_path(self, key: str) -> str:
        """The data file of data set ``key``."""
        folder = self.out / "data" if self.preset.in_out else Path("data")
        return str(folder / self.preset.datasets[key].file)

    def generator_config(self, key: str):
        """Its resolved generator config (``python -m jaxcal.generate`` parsing)."""
        from jaxcal.cli.generate import parse_args

        spec = self.preset.datasets[key]
        cfg, _ = parse_args([f"dataset={spec.generator}", *spec.overrides])
        return cfg

    def train_argv(self, key: str, agent: str) -> list[str]:
        """The training command line of one run (deterministic run name)."""
        from jaxcal.cli.train import parse_args
        from jaxcal.training.config import make_train_config

        spec = self.preset.datasets[key]
        # AGENTS: e.g. "clac-f" -> agent=clac dynamics=physics (method CLAC-F)
        argv = [f"dataset={spec.train_dataset}", *AGENTS[agent][1]]
        default = (
            self.data_path(key) == make_train_config(spec.train_dataset).dataset.path
        )
        if not default:
            argv.append(f"path={self.data_path(key)}")
        extra = list(self.preset.train_args.get(key, ()))
        if any(a.startswith("preset=") for a in extra):  # the quick run's smoke
            argv += list(FEEDBACK) if agent == "clac-inc" else []
        else:
            argv.append("preset=default" if agent == "clac-inc" else "preset=absolute")
        argv += extra
        if self.preset.in_out:
            argv.append(f"output.runs_dir={self.out / 'runs'}")
        if self.seed:
            argv.append(f"seed={self.seed}")
        try:
            cfg = parse_args(argv)
        except ValueError as err:
            raise ValueError(
                f"training of {AGENTS[agent][0]} on {key}: {err} (skip="
                f"{AGENTS[agent][0]} leaves the method out)"
            ) from None
        name = cfg.run_name
        if not default:  # not the CLI's own file: a name of its own, never regenerated
            name = name.replace(cfg.dataset.name, Path(spec.file).stem, 1)
        if not default or name != cfg.run_name:
            argv.append(f"name={name}")
        if not default:
            argv.append("dataset.generate=")
        return argv

    def run_dir(self, key: str, agent: str) -> str:
        """The run folder of one training (from its command line, no training)."""
        from jaxcal.cli.train import parse_args

        cfg = parse_args(self.train_argv(key, agent))
        return str(Path(cfg.output.runs_dir) / cfg.run_name)

    def agents(self, key: str) -> tuple[str, ...]:
        """The policies trained on data set ``key`` (CLAC always; the others of
        :data:`AGENTS` on ds1, unless skipped)."""
        extra = tuple(a for a in AGENTS if a != "clac") if key == "ds1" else ()
        return ("clac",) + tuple(
            a for a in extra if (key, AGENTS[a][0]) not in self.preset.skip
        )

    def suite(self, key: str):
        """The :class:`~jaxcal.paper.suite.Suite` of ``key`` (built once)."""
        from jaxcal.paper.suite import Suite

        if key not in self._suites:
            runs = {AGENTS[a][0]: self.run_dir(key, a) for a in self.agents(key)}
            # F runs in the generator's chunks: one compiled program for both
            chunk = self.generator_config(key).chunk_size
            cfg = dataclasses.replace(self.preset.suites[key], chunk_size=chunk)
            self._suites[key] = Suite(
                self.data_path(key), runs, cfg, self.out / "models" / key
            )
        return self._suites[key]


def estimate(preset: Preset, name: str) -> float:
    """Expected seconds of step ``name``: the longest matching prefix in the preset."""
    keys = [k for k in preset.estimates if name.startswith(k)]
    return float(preset.estimates[max(keys, key=len)]) if keys else 30.0


def make_plan(ctx: Context) -> list[Step]:
    """Every step of the experiment, in order."""
    from jaxcal.calibrators.methods.policy.gated import DEFAULT_WINDOW
    from jaxcal.paper import gate_steps, npe_steps
    from jaxcal.paper.npe import is_available as npe_available
    from jaxcal.paper.std_steps import calib_std_step
    from jaxcal.paper.steps import ensure_dataset

    preset, steps = ctx.preset, []

    def add(name: str, config: dict, work: Callable[[], dict]) -> None:
        steps.append(Step(name, estimate(preset, name), config, work))

    for key in preset.datasets:
        cfg = ctx.generator_config(key)
        add(
            f"data-{key}",
            {"generator": preset.datasets[key].generator, "seed": cfg.seed,
             "overrides": list(preset.datasets[key].overrides),
             "path": ctx.data_path(key)},
            lambda cfg=cfg, key=key: ensure_dataset(cfg, ctx.data_path(key)),
        )  # fmt: skip
    trainings = [("ds1", a) for a in ctx.agents("ds1")] + [
        (k, "clac") for k in ("ds2", *preset.scalability)
    ]
    for key, agent in trainings:
        argv = ctx.train_argv(key, agent)
        add(
            f"train-{key}-{agent}",
            {"argv": argv, "seed": ctx.seed},
            lambda argv=argv: train_or_reuse(argv),
        )
    for key in preset.suites:
        add(
            f"check-{key}",
            {"num_samples": 2048, "seed": ctx.seed},
            lambda key=key: ctx.suite(key).model_gap(num_samples=2048, seed=ctx.seed),
        )
    for key in ("ds1", "ds2"):
        for name in (n for n in ("E2E", "E2E-sim") if (key, n) not in preset.skip):
            cfg = preset.suites[key]
            add(
                f"fit-{key}-{name}",
                {"seed": ctx.seed, "e2e": dataclasses.asdict(cfg.e2e),
                 "labelled_units": list(cfg.e2e_units) or "training units",
                 "max_samples": cfg.e2e_max_samples},
                lambda key=key, name=name: ctx.suite(key).fit_e2e(name, seed=ctx.seed),
            )  # fmt: skip
    if not {("ds1", m) for m in ("CLAC-inc", "CLAC-gate")} & set(preset.skip):
        add(
            "fit-ds1-CLAC-gate",
            {"window": DEFAULT_WINDOW, "units": "validation", "seed": ctx.seed},
            lambda: gate_steps.fit_step(ctx.suite("ds1")),
        )
    npe_cfg = preset.suites["ds1"].npe
    with_npe = ("ds1", "NPE") not in preset.skip and npe_available()
    if with_npe:  # without sbi the report says how to install it (npe_table)
        add(
            "fit-ds1-NPE",
            {"seed": ctx.seed, "npe": dataclasses.asdict(npe_cfg)},
            lambda: npe_steps.fit_step(ctx.suite("ds1"), npe_cfg, seed=ctx.seed),
        )
    evals = [
        (key, variant, method)
        for key, variant, methods in EVALUATIONS
        for method in methods
        if key in preset.suites and (key, method) not in preset.skip
    ]
    for key, variant, method in evals:
        name = f"eval-{key}-{method}-{variant}"
        bias, sigma = VARIANTS.get(variant, (1.0, 0.0))
        add(
            name,
            {"method": method, "variant": variant, "bias": bias, "noise_sigma": sigma,
             "seed": ctx.seed},
            lambda key=key, variant=variant, method=method, name=name: evaluate(
                ctx, key, variant, method, name
            ),
        )  # fmt: skip
    if ("ds1", "UKF") not in preset.skip:  # the UKF's std, rescaled on val units
        add(
            "calib-ds1-UKF",
            {"method": "UKF", "level": 0.9, "fit_on": "validation units",
             "seed": ctx.seed},
            lambda: calib_std_step(ctx.suite("ds1"), "UKF", seed=ctx.seed),
        )  # fmt: skip
    if with_npe:
        add(
            "eval-ds1-NPE-clean",
            {"method": "NPE", "variant": "clean", "seed": ctx.seed},
            lambda: npe_steps.evaluate_step(ctx.suite("ds1"), npe_cfg, seed=ctx.seed),
        )
    for method in (m for m in ALL_METHODS if ("ds1", m) not in preset.skip):
        add(
            f"latency-ds1-{method}",
            {"method": method, "repeats": preset.latency_repeats, "seed": ctx.seed},
            lambda method=method: ctx.suite("ds1").latency(
                method, repeats=preset.latency_repeats, seed=ctx.seed
            ),
        )
    if with_npe:
        add(
            "latency-ds1-NPE",
            {"method": "NPE", "repeats": preset.latency_repeats, "seed": ctx.seed},
            lambda: npe_steps.latency_step(
                ctx.suite("ds1"), npe_cfg, repeats=preset.latency_repeats, seed=ctx.seed
            ),
        )
    for key in preset.identifiability:
        add(f"ident-{key}", {"traces": "clean", "seed": ctx.seed},
            lambda key=key: identifiability(ctx, key))  # fmt: skip
    add("figures", {}, lambda: make_figures(ctx.out, ctx.preset.scalability))
    return steps


def train_or_reuse(argv: list[str], *, log: Callable[[str], None] = print) -> dict:
    """A trained policy: the run of ``python -m jaxcal.train <argv>``, reused if done.

    Training runs in-process through the CLI's own ``main`` in the CLI's precision
    (float64 for a policy on the engines' F, else float32), whatever the caller's.

    Args:
        argv: the training command line (``key=value`` tokens).
        log: printer.

    Returns:
        The run's ``final.json`` plus ``{"run_dir", "reused", "argv"}``;
        ``time_to_target_s`` (the issue's training-speed measure) is copied from it,
        null when the training job did not record it.

    Raises:
        ValueError: the run folder holds a run of another config.
        RuntimeError: the training CLI failed.
    """
    import jax

    from jaxcal.cli.train import main, parse_args
    from jaxcal.runs.folder import FINAL_FILE, prepare_run_dir, read_json

    cfg = parse_args(argv)
    run_dir = Path(cfg.output.runs_dir) / cfg.run_name
    final_path = run_dir / FINAL_FILE
    reused = final_path.is_file()
    if reused:
        prepare_run_dir(run_dir, cfg)  # raises when the stored config differs
        log(f"reusing {run_dir} (final.json present)")
    else:
        log("python -m jaxcal.train " + " ".join(argv))
        # the CLI's own precision: float64 around the engines' Newton solve when the
        # policy trains on F (dynamics=physics), else float32
        with jax.enable_x64(cfg.dynamics == "physics"):
            code = main(list(argv))
        if code != 0:
            raise RuntimeError(f"training failed (exit code {code}): {argv}")
    final = read_json(final_path)
    # the training-speed measure; null when the training job did not record it
    final.setdefault("time_to_target_s", None)
    return {**final, "run_dir": str(run_dir), "reused": reused, "argv": list(argv)}


def evaluate(ctx: Context, key: str, variant: str, method: str, name: str) -> dict:
    """One evaluation step: scores (returned) and the traces for the figures (npz)."""
    suite = ctx.suite(key)
    bias, sigma = VARIANTS.get(variant, (1.0, 0.0))
    data = ctx.data_path("ds1-snr70") if variant == "snr70" else None
    run = suite.evaluate(
        method, seed=ctx.seed, bias=bias, noise_sigma=sigma, data_path=data
    )
    save_traces(ctx.out / "traces" / f"{name}.npz", run, suite.test_units(data), suite)
    return {"dataset": key, "variant": variant, **run.scores}


def identifiability(ctx: Context, key: str) -> dict:
    """The weakest direction of each test unit of ``key`` and every method's error
    along it and across it (:mod:`jaxcal.paper.identifiability`), from the clean
    evaluations' traces."""
    import numpy as np

    from jaxcal.paper.identifiability import identifiability_study

    suite, traces, stride = ctx.suite(key), {}, None
    for method in ALL_METHODS:
        path = ctx.out / "traces" / f"eval-{key}-{method}-clean.npz"
        if not path.is_file():
            continue
        with np.load(path) as t:
            traces[method], stride = t["theta"], int(t["stride"])
    if not traces:
        raise FileNotFoundError(f"no clean traces of {key} under {ctx.out / 'traces'}")
    return identifiability_study(
        suite.engine, suite.problem, suite.test_units(), traces, stride=stride
    )


# ----------------------------------------------------------------------- main

USAGE = (
    "usage: python experiments/paper.py [preset=full|quick] [out=DIR] [seed=N] "
    "[skip=LS,SAC,...]"
)


SKIPPABLE = (
    "UKF",
    *ON_MODEL,  # every registered method on the model beside the UKF
    "E2E",
    "E2E-sim",
    "LAC",
    "SAC",
    "CLAC-F",
    "CLAC-inc",
    "CLAC-gate",
    "NPE",
)


def parse_args(argv: list[str]) -> tuple[Preset, Path, int]:
    """``(preset, out, seed)`` from ``key=value`` tokens; a bad token is an error.

    ``skip=LS,SAC`` leaves methods out on every data set (with their trainings and
    fits): a shorter run, with "–" in the report where they would be.
    """
    args: dict[str, str] = {}
    for token in argv:
        key, sep, value = token.partition("=")
        if not sep or key not in ("preset", "out", "seed", "skip") or key in args:
            raise ValueError(
                f"bad argument {token!r}: expected preset=, out=, seed= or skip= "
                "once each"
            )
        args[key] = value
    name = args.get("preset", "full")
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {list(PRESETS)}")
    default_out = "results/paper" if name == "full" else "results/paper-quick"
    try:
        seed = int(args.get("seed", "0"))
    except ValueError:
        raise ValueError(f"seed must be an integer, got {args['seed']!r}") from None
    skip = [m for m in args.get("skip", "").split(",") if m]
    if "CLAC-inc" in skip and "CLAC-gate" not in skip:  # the gate needs CLAC-inc
        skip.append("CLAC-gate")
    unknown = [m for m in skip if m not in SKIPPABLE]
    if unknown:
        raise ValueError(f"skip: unknown method(s) {unknown}; choose from {SKIPPABLE}")
    preset = PRESETS[name]
    if skip:
        extra = tuple((key, m) for key in preset.suites for m in skip)
        preset = dataclasses.replace(preset, skip=preset.skip + extra)
    return preset, Path(args.get("out") or default_out), seed


def main(argv: list[str] | None = None) -> int:
    """Run (or resume) the experiment and write the report; returns the exit code."""
    from jaxcal.cli.args import parse_command_line

    argv = sys.argv[1:] if argv is None else list(argv)
    parsed, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if parsed is None:
        return code
    preset, out, seed = parsed
    from tqdm import tqdm

    from jaxcal.cache import enable_compilation_cache
    from jaxcal.paper.report import write_report
    from jaxcal.paper.steps import StepStore, format_seconds

    enable_compilation_cache()
    start = time.perf_counter()
    ctx = Context(preset, out, seed)
    store = StepStore(out, log=tqdm.write)
    plan = make_plan(ctx)
    todo = [s for s in plan if not store.done(s.name)]
    print(f"paper: preset={preset.name} seed={seed} out={out}; {len(plan)} steps, "
          f"{len(plan) - len(todo)} done; estimate for the rest "
          f"{format_seconds(sum(s.estimate_s for s in todo))}:")  # fmt: skip
    for s in plan:
        state = "done" if store.done(s.name) else format_seconds(s.estimate_s)
        print(f"  {s.name:<32} {state}")
    if any(s.name != "figures" for s in todo):  # new results: draw the figures again
        store.path("figures").unlink(missing_ok=True)
    for step in tqdm(plan, desc="paper", unit="step", dynamic_ncols=True):
        store.run(step.name, step.work, estimate_s=step.estimate_s, config=step.config)
    results = {s.name: store.read(s.name) for s in plan}
    # a step that found its optional extra broken ({"skipped": why}) is left out of
    # the report (its table says why) and run again next time
    for name in [n for n, res in results.items() if "skipped" in res]:
        store.path(name).unlink()
        del results[name]
    report = write_report(
        out / "REPORT.md",
        results,
        preset=preset.name,
        description=preset.description,
        seed=seed,
        command=" ".join(["python experiments/paper.py", *argv]),
        wall_seconds=time.perf_counter() - start,
    )
    print(f"report: {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
