"""Hostile input at the front door (issue 25): build each case, classify what it gives.

Issue 25 lists inputs a careless user or a faulty pipeline gives ``jaxcal.Model``,
``jaxcal.calibrate``, ``model=`` on the command lines and run folders, by class. This
script builds one or more small cases per class on a tiny tank model (seconds each)
and classifies the outcome by rules, not by hand, so the same script can be run on
the code before the issue and after it and the two compared:

* ``clear error``: a ``ValueError`` (or an exception class of jaxcal's own) raised
  by jaxcal's code, whose message names the field, file, row or name involved (the
  case lists the words; one must appear); for a command line: exit code 2, no
  traceback, and the name on stderr;
* ``flagged result``: a correct result and the flag the case needs (a console
  warning, ``valid`` / ``reason`` / ``partial`` of the result);
* ``correct result``: a correct result where the input was legitimate and nothing
  needed a flag (a DataFrame indexed by unit and time; a run whose model file moved);
* ``silent wrong``: a result that is wrong, or one that needed a flag and has none;
* ``raw crash``: any other exception (raised inside JAX, numpy, pandas or Python,
  or a message that does not name the user's thing), or a command line that exits
  with another code or a traceback.

Run it from the tree to probe (the old tree as a worktree on ``PYTHONPATH``)::

    JAX_PLATFORMS=cpu .venv/bin/python experiments/hostile_probe.py \
        out=results/hostile label=after
    cd /tmp/before && JAX_PLATFORMS=cpu PYTHONPATH=/tmp/before \
        /work/main/.venv/bin/python /work/main/experiments/hostile_probe.py \
        out=/work/main/results/hostile label=before
    .venv/bin/python experiments/hostile_probe.py report=results/hostile

The first two write ``<out>/<label>.json`` (one record per case: class, case,
outcome, message excerpt, what was measured); ``report=`` writes
``<dir>/README.md``, the table of the issue (class, cases, before, after, the test
that covers the class) from the two files. Only names both trees have are imported
at module level; newer ones are imported inside the cases that need them.
"""

from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# the innermost frame of an error must be where it was raised (raw or jaxcal's)
os.environ["JAX_TRACEBACK_FILTERING"] = "off"

import dataclasses  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

import jaxcal  # noqa: E402

OUTCOMES = (
    "clear error",
    "flagged result",
    "correct result",
    "silent wrong",
    "raw crash",
)
CLASSES = (
    "model contract",
    "tables",
    "one bad reading",
    "skipped rows",
    "model files",
    "runs",
    "memory",
    "partial observations",
)
# the tests that hold each class on the current tree (file::test)
TESTS = {
    "model contract": [
        "tests/test_model_contract.py::"
        "test_an_output_that_breaks_the_declaration_is_a_clear_error",
        "tests/test_model_contract.py::"
        "test_name_clashes_and_reserved_names_are_refused_at_construction",
        "tests/test_model_contract.py::"
        "test_a_parameter_spec_of_another_form_lists_the_accepted_forms",
    ],
    "tables": [
        "tests/data/test_hostile_tables.py::"
        "test_an_index_of_units_and_times_is_read_as_those_columns",
        "tests/data/test_hostile_tables.py::test_a_time_repeated_within_a_unit_is_named",
        "tests/data/test_hostile_tables.py::test_a_unit_in_two_splits_is_named",
    ],
    "one bad reading": [
        "tests/calibrators/test_hostile_front.py::"
        "test_one_wild_reading_changes_no_other_unit_and_is_flagged",
        "tests/calibrators/test_hostile_front.py::"
        "test_impossible_operating_points_are_outliers_not_noise",
    ],
    "skipped rows": [
        "tests/calibrators/test_hostile_front.py::"
        "test_skipped_rows_report_the_prior_or_the_carried_estimate",
        "tests/calibrators/test_hostile_front.py::"
        "test_a_noise_so_small_that_every_row_is_skipped_is_an_error",
        "tests/calibrators/test_hostile_front.py::"
        "test_a_noise_outside_float32_is_named_with_the_dtype",
        "tests/calibrators/test_hostile_front.py::"
        "test_a_model_nan_in_part_of_the_box_is_named_as_the_cause",
    ],
    "model files": [
        "tests/test_model_files.py::test_train_exits_2_with_one_line",
        "tests/test_model_files.py::test_diagnose_process_exits_2_without_a_traceback",
    ],
    "runs": [
        "tests/training/test_run_safety.py::"
        "test_run_names_outside_the_runs_folder_are_refused",
        "tests/training/test_run_safety.py::"
        "test_a_second_training_of_a_run_in_use_exits_2_and_nothing_interleaves",
        "tests/training/test_run_safety.py::"
        "test_a_run_does_not_follow_later_edits_of_its_model_file",
        "tests/training/test_run_safety.py::"
        "test_loading_a_run_never_imports_a_path_outside_it",
    ],
    "memory": [
        "tests/calibrators/test_hostile_front.py::"
        "test_a_skewed_fleet_is_padded_in_groups_of_similar_length",
    ],
    "partial observations": [
        "tests/calibrators/test_partial.py::"
        "test_front_door_uses_partial_rows_and_flags_them",
    ],
}
LIBRARY = os.path.dirname(os.path.abspath(jaxcal.__file__))
MEMORY_BUDGET = 2e9  # bytes: the old padding is projected, not run, beyond this
LONG, SHORT = 100_000, 2_000  # the memory case: one long unit, many one-row units
NOISE = np.array([0.02, 0.02, 0.05])
OUTPUTS = ("level", "temp", "outflow")
GIVEN = dict(zip(OUTPUTS, NOISE.tolist(), strict=True))
TOY_SOURCE = '''"""A toy model for the probe's runs."""
import jax.numpy as jnp
import jaxcal


def toy(w, theta):
    a, b = w[0], w[1]
    p, q = theta[0], theta[1]
    return jnp.stack([p * a + q * b, p * q + 0.5 * a, p - q * a * b])


MODEL = jaxcal.Model.from_function(
    toy,
    conditions={"a": "m", "b": "s"},
    parameters={"p": (1.0, 0.5, 2.0, "-"), "q": (0.5, 0.1, 1.0, "-")},
    outputs=("y1", "y2", "y3"),
    name="toy",
)
'''
TOY_EDITED = TOY_SOURCE.replace("p * a + q * b", "3.0 * p * a + q * b")


# --------------------------------------------------------------------------- model


def tank(w, theta):
    """A leaky tank heated by w[0] with inflow w[1]: level, temperature, outflow."""
    heat, inflow = w[0], w[1]
    leak, loss = theta[0], theta[1]
    level = inflow / leak
    temp = 20.0 + heat / (inflow * (1.0 + loss))
    return jnp.stack([level, temp, leak * level * (1.0 - 0.1 * loss)])


def tank_model(fn=tank, *, name="tank", box=True, **changes):
    """``fn`` declared as the tank; ``changes`` replace any of its declarations."""
    spec = dict(
        conditions={"heat": "kW", "inflow": "kg/s"},
        parameters={"leak": (1.0, 0.5, 2.0, "1/s"), "loss": (0.1, 0.0, 0.5)},
        outputs={"level": "m", "temp": "degC", "outflow": "kg/s"},
        condition_range=([0.0, 0.1], [50.0, 5.0]) if box else None,
        name=name,
    )
    spec.update(changes)
    return jaxcal.Model.from_function(fn, **spec)


def tank_frame(num_units=3, length=40, seed=0):
    """``num_units`` units of ``length`` rows, leak drifting, rows in time order."""
    rng = np.random.default_rng(seed)
    n = num_units * length
    t = np.tile(np.arange(length), num_units)
    w = np.stack([rng.uniform(5, 30, n), rng.uniform(0.5, 2.0, n)], 1)
    leak = 1.0 + 0.3 * t / length + 0.1 * np.repeat(np.arange(num_units), length)
    theta = np.stack([leak, np.full(n, 0.2)], 1)
    x = np.asarray(jax.vmap(tank)(w, theta)) + NOISE * rng.standard_normal((n, 3))
    frame = pd.DataFrame({"heat": w[:, 0], "inflow": w[:, 1]})
    for j, name in enumerate(OUTPUTS):
        frame[name] = x[:, j]
    frame["unit"], frame["time"] = np.repeat(np.arange(num_units), length), t
    return frame


# ------------------------------------------------------------------ classification


@dataclasses.dataclass
class Seen:
    """What a case saw when it did not raise.

    Attributes:
        correct: the result is right (the case's own check).
        flagged: the flag the case needs is there.
        needs_flag: a correct result still needs a flag (the input was not
            legitimate as given).
        detail: what was measured, for the record.
        outcome: set directly by a command-line case (exit code and stderr).
        message: stderr of a command line, or the flag's words.
    """

    correct: bool
    flagged: bool = False
    needs_flag: bool = True
    detail: dict = dataclasses.field(default_factory=dict)
    outcome: str | None = None
    message: str = ""


@dataclasses.dataclass
class Case:
    """One hostile input: its class, its name, what a clear error names, the run."""

    klass: str
    name: str
    names: tuple[str, ...]
    run: Callable[[Context], Seen]


def _raised_by_library(err: BaseException) -> bool:
    """The innermost frame of ``err`` is jaxcal's code, or its class is jaxcal's."""
    frames = traceback.extract_tb(err.__traceback__)
    inner = os.path.abspath(frames[-1].filename) if frames else ""
    own_class = type(err).__module__.split(".")[0] == "jaxcal"
    return inner.startswith(LIBRARY + os.sep) or own_class


def classify_error(err: BaseException, names: tuple[str, ...]) -> tuple[str, str]:
    """``(outcome, message excerpt)`` of an exception (module docstring)."""
    text = f"{type(err).__name__}: {err}"
    own_class = type(err).__module__.split(".")[0] == "jaxcal"
    kind = isinstance(err, ValueError) or own_class
    named = any(n.lower() in text.lower() for n in names)
    clear = kind and named and _raised_by_library(err)
    return ("clear error" if clear else "raw crash"), _excerpt(text)


def classify_seen(seen: Seen) -> str:
    """The outcome of a case that returned (module docstring)."""
    if seen.outcome is not None:
        return seen.outcome
    if not seen.correct:
        return "silent wrong"
    if seen.flagged:
        return "flagged result"
    return "silent wrong" if seen.needs_flag else "correct result"


def classify_cli(proc, names: tuple[str, ...]) -> str | None:
    """A command line's outcome, or ``None`` when it exited 0 (the case looks at
    what it did)."""
    if proc.returncode == 0:
        return None
    err = proc.stderr
    named = any(n.lower() in err.lower() for n in names)
    if proc.returncode == 2 and "Traceback" not in err and named:
        return "clear error"
    return "raw crash"


def _excerpt(text: str, size: int = 400) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= size else text[: size - 3] + "..."


def _stderr_excerpt(err: str) -> str:
    """The last lines of a command's stderr (its error, after any traceback)."""
    lines = [line for line in err.strip().splitlines() if line.strip()]
    return _excerpt(" | ".join(lines[-3:]))


# ------------------------------------------------------------------------- context


class Context:
    """Shared inputs of the cases, built on first use (a reference calibration, a
    trained run), and a scratch folder removed at the end."""

    def __init__(self, root: Path):
        self.root = root
        self._cache: dict = {}

    def cached(self, key, build):
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    @property
    def model(self):
        return self.cached("model", tank_model)

    @property
    def frame(self):
        return self.cached("frame", tank_frame)

    @property
    def reference(self):
        """The UKF on the clean frame with the given noise."""
        return self.cached(
            "reference", lambda: calibrate(self.model, self.frame, "ukf", GIVEN)[0]
        )

    def env(self) -> dict:
        """The environment of a child process: this tree's jaxcal, CPU."""
        path = os.path.dirname(LIBRARY)
        extra = os.environ.get("PYTHONPATH", "")
        return {
            **os.environ,
            "JAX_PLATFORMS": "cpu",
            "PYTHONPATH": path + (os.pathsep + extra if extra else ""),
        }

    def cli(self, module: str, *args: str, cwd: Path | None = None, timeout=900):
        return subprocess.run(
            [sys.executable, "-m", module, *args],
            capture_output=True,
            text=True,
            env=self.env(),
            cwd=cwd or self.root,
            timeout=timeout,
            check=False,
        )

    @property
    def toy(self):
        """The toy model file, its data and one trained run ``toy`` (a policy with
        ``dynamics=physics``, so tracking runs the model itself)."""
        return self.cached("toy", self._train_toy)

    def toy_argv(self, name: str, runs: Path | None = None) -> list[str]:
        root = self.root / "toy"
        return [
            f"model={root / 'toy_model.py'}:MODEL",
            f"data={root / 'toy.csv'}",
            "theta=p,q",
            "preset=smoke",
            "dynamics=physics",
            f"output.runs_dir={runs or root / 'runs'}",
            "output.progress=false",
            f"name={name}",
        ]

    def _train_toy(self):
        root = self.root / "toy"
        root.mkdir()
        (root / "toy_model.py").write_text(TOY_SOURCE)
        model = jaxcal.models.load(f"{root / 'toy_model.py'}:MODEL")
        rng = np.random.default_rng(0)
        rows = []
        for unit in range(1, 7):
            w = np.stack([rng.uniform(0.5, 1.5, 30), rng.uniform(0.2, 1.0, 30)], 1)
            theta = np.stack(
                [1.0 + 0.02 * unit + 0.002 * np.arange(30), np.full(30, 0.4)], 1
            )
            x = np.asarray(jax.vmap(lambda a, t: model.evaluate(a, t)[0])(w, theta))
            x = x + 1e-3 * rng.standard_normal(x.shape)
            cols = {"unit": unit, "time": np.arange(30), "a": w[:, 0], "b": w[:, 1]}
            cols.update({f"y{j + 1}": x[:, j] for j in range(3)})
            rows.append(pd.DataFrame(cols))
        pd.concat(rows, ignore_index=True).to_csv(root / "toy.csv", index=False)
        proc = self.cli("jaxcal.train", *self.toy_argv("toy"), cwd=root)
        if proc.returncode != 0:
            raise RuntimeError(f"training the toy run failed: {proc.stderr[-2000:]}")
        return {
            "root": root,
            "file": root / "toy_model.py",
            "csv": root / "toy.csv",
            "run": root / "runs" / "toy",
        }


def calibrate(model, data, method="ukf", noise=None, **options):
    """``jaxcal.calibrate`` with its warnings kept: ``(result, words)`` where
    ``words`` are the warnings and the result's notes."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxcal.calibrate(model, data, method, noise=noise, **options)
    words = [str(w.message) for w in caught]
    words += list(getattr(result, "notes", ()) or ())
    return result, " | ".join(words)


def _close(result, reference, rows=None, tol=0.1) -> float:
    """Largest change of theta against ``reference`` in its stds (on ``rows``)."""
    rows = slice(None) if rows is None else rows
    std = reference.theta_std[rows]
    return float(np.max(np.abs(result.theta[rows] - reference.theta[rows]) / std))


# ----------------------------------------------------------------- model contract


def _contract_case(fn, **changes):
    def run(ctx: Context) -> Seen:
        model = tank_model(fn, name="user", **changes)
        result, words = calibrate(model, ctx.frame, "ukf", GIVEN)
        change = _close(result, ctx.reference)
        return Seen(
            correct=bool(change < 0.1),
            flagged="output" in words.lower(),
            detail={"largest theta change (ref stds)": change},
            message=words,
        )

    return run


def _stateful_case(step, init_state):
    def run(ctx: Context) -> Seen:
        model = jaxcal.Model.from_step(
            step,
            init_state=init_state,
            states=("z",),
            conditions=("heat", "inflow"),
            parameters={"leak": (1.0, 0.5, 2.0), "loss": (0.1, 0.0, 0.5)},
            outputs=OUTPUTS,
            name="user",
        )
        result, words = calibrate(model, ctx.frame, "ukf", GIVEN)
        return Seen(correct=False, flagged=False, message=words)

    return run


def _clash_case(clash: str, column_of: dict, **changes):
    """A model whose name ``clash`` is also a column the reader knows; the frame as
    its user would write it (``column_of``: the model's name -> the column it
    replaces)."""

    def run(ctx: Context) -> Seen:
        model = tank_model(name="user", **changes)
        frame = ctx.frame.copy()
        for name, column in column_of.items():
            frame[name] = frame.pop(column)
        noise = dict(zip(model.output_names, NOISE.tolist(), strict=True))
        result, words = calibrate(model, frame, "ukf", noise)
        return Seen(
            correct=False,  # one column read two ways: no result can be right
            flagged=f"'{clash}'" in words,
            message=words,
            detail={"units seen": int(len(np.unique(result.unit)))},
        )

    return run


def _parameter_spec(ctx: Context) -> Seen:
    model = tank_model(name="user", parameters={"leak": 1.0, "loss": (0.1, 0.0, 0.5)})
    result, words = calibrate(model, ctx.frame, "ukf", GIVEN)
    return Seen(correct=False, message=words)


def contract_cases() -> list[Case]:
    k = "model contract"
    outs = ("'level'", "'temp'", "'outflow'", "declared output")
    state = ("next_state", "['z']", "'z'", "declared state")

    def scalar(w, t):
        return tank(w, t)[0]

    def as_list(w, t):
        x = tank(w, t)
        return [x[0], x[1], x[2]]

    def only_x(z, w, t):
        return tank(w, t)

    def two_states(w0, t):
        return jnp.zeros(2)

    def step(z, w, t):
        return z, tank(w, t)

    return [
        Case(k, "fn returns 2 of 3 outputs", outs,
             _contract_case(lambda w, t: tank(w, t)[:2])),
        Case(k, "fn returns 4 values for 3 outputs", outs,
             _contract_case(lambda w, t: jnp.concatenate([tank(w, t), w[:1]]))),
        Case(k, "fn returns a scalar", outs, _contract_case(scalar)),
        Case(k, "fn returns a list", outs, _contract_case(as_list)),
        Case(k, "fn returns a [3, 1] array", outs,
             _contract_case(lambda w, t: tank(w, t)[:, None])),
        Case(k, "step fn returns only x", state, _stateful_case(only_x, np.zeros(1))),
        Case(k, "init_state of the wrong size", state,
             _stateful_case(step, two_states)),
        Case(k, "an output named time", ("'time'",),
             _clash_case("time", {"time": "outflow"},
                         outputs=("level", "temp", "time"))),
        Case(k, "a parameter named like a condition", ("'heat'",),
             _clash_case("heat", {}, parameters={"leak": (1.0, 0.5, 2.0),
                                                 "heat": (0.1, 0.0, 0.5)})),
        Case(k, "an output named unit", ("'unit'",),
             _clash_case("unit", {"unit": "outflow"},
                         outputs=("level", "temp", "unit"))),
        Case(k, "parameter spec {'leak': 1.0}", ("'leak'",), _parameter_spec),
    ]  # fmt: skip


# -------------------------------------------------------------------------- tables


def _indexed(ctx: Context) -> Seen:
    frame = ctx.frame.set_index(["unit", "time"])
    result, words = calibrate(ctx.model, frame, "ukf", GIVEN)
    units = int(len(np.unique(result.unit)))
    change = _close(result, ctx.reference)
    return Seen(
        correct=bool(units == 3 and change < 1e-6),
        needs_flag=False,
        detail={"units read": units, "largest theta change (ref stds)": change},
        message=words,
    )


def _result_needs_word(frame_of, word, **options):
    """A table that can be read only by guessing: any result needs a word."""

    def run(ctx: Context) -> Seen:
        result, words = calibrate(ctx.model, frame_of(ctx), "ukf", GIVEN, **options)
        return Seen(correct=False, flagged=word in words, message=words)

    return run


def _two_level_columns(ctx: Context):
    extra = ctx.frame[["outflow"]].rename(columns={"outflow": "level"})
    return pd.concat([ctx.frame, extra], axis=1)


def _header_only(ctx: Context) -> Seen:
    path = ctx.root / "header_only.csv"
    path.write_text("unit,time,heat,inflow,level,temp,outflow\n")
    result, words = calibrate(ctx.model, path, "ukf", GIVEN)
    return Seen(correct=False, message=words)


def _data_of_type(value):
    def run(ctx: Context) -> Seen:
        result, words = calibrate(ctx.model, value, "ukf", GIVEN)
        return Seen(correct=False, message=words)

    return run


def _ignored_output(ctx: Context) -> Seen:
    noise = {k: v for k, v in GIVEN.items() if k != "temp"}
    result, words = calibrate(ctx.model, ctx.frame, "ukf", noise, ignore=("temp",))
    used = tuple(result.output_names)
    return Seen(
        correct=bool("temp" not in used and result.valid.all()),
        needs_flag=False,
        detail={"outputs used": list(used)},
        message=words,
    )


def _repeated_time(ctx: Context):
    frame = ctx.frame.copy()
    frame.loc[(frame.unit == 1) & (frame.time == 5), "time"] = 6
    return frame


def _straddling_split(ctx: Context) -> Seen:
    frame = ctx.frame.assign(split=np.where(np.arange(len(ctx.frame)) % 2, "test",
                                            "train"))  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = jaxcal.read_dataset(frame, ctx.model)
    words = " | ".join(str(w.message) for w in caught)
    split, unit = np.asarray(data.split).astype(str), np.asarray(data.unit)
    both = set(unit[split == "train"]) & set(unit[split == "test"])
    return Seen(
        correct=not both,
        flagged="split" in words,
        detail={"units in train and test": len(both)},
        message=words,
    )


def table_cases() -> list[Case]:
    k = "tables"
    types = ("DataFrame",)
    return [
        Case(k, "DataFrame indexed by (unit, time)", ("unit", "index"), _indexed),
        Case(k, "two columns named level", ("'level'",),
             _result_needs_word(_two_level_columns, "level")),
        Case(k, "rename= onto an existing name", ("'temp'",),
             _result_needs_word(lambda c: c.frame.assign(z=c.frame.temp + 1.0),
                                "temp", rename={"z": "temp"})),
        Case(k, "empty DataFrame", ("no rows", "empty"),
             _result_needs_word(lambda c: c.frame.iloc[:0], "no rows")),
        Case(k, "header-only CSV", ("header_only.csv",), _header_only),
        Case(k, "ndarray as data", types, _data_of_type(np.zeros((4, 7)))),
        Case(k, "list as data", types, _data_of_type([[1.0, 2.0, 3.0]])),
        Case(k, "None as data", types, _data_of_type(None)),
        Case(k, "ignore= of a condition the model needs", ("'heat'",),
             _result_needs_word(lambda c: c.frame, "heat", ignore=("heat",))),
        Case(k, "ignore= of an output", ("'temp'",), _ignored_output),
        Case(k, "a time repeated within a unit", ("time",),
             _result_needs_word(_repeated_time, "time")),
        Case(k, "split alternating inside units", ("split",), _straddling_split),
    ]  # fmt: skip


# ----------------------------------------------------------------- one bad reading


def _wild(method: str, spoil: Callable, estimate=True, **options):
    """An unboxed tank (so that a negative flow reaches the model) calibrated on a
    frame whose unit 1 ``spoil`` spoils: every stream must go on as if the spoiled
    rows had not come (within 0.1 of a std), the noise estimate stay within 10 %
    of the clean one, and the rows be flagged."""

    def run(ctx: Context) -> Seen:
        model = ctx.cached("open", lambda: tank_model(name="open", box=False))
        frame = ctx.cached("frame4", lambda: tank_frame(num_units=4))
        noise = None if estimate else GIVEN
        clean = ctx.cached(
            ("clean", method, estimate),
            lambda: calibrate(model, frame, method, noise, **options)[0],
        )
        bad, rows = spoil(frame.copy())
        result, words = calibrate(model, bad, method, noise, **options)
        without, _ = calibrate(model, frame.drop(index=rows), method, noise, **options)
        kept = np.delete(np.arange(len(frame)), rows)
        change = np.abs(result.theta[kept] - without.theta) / without.theta_std
        others = (frame.unit != 1).to_numpy()[kept]
        ratio = np.asarray(result.problem.noise_std) / np.asarray(
            clean.problem.noise_std
        )
        detail = {
            "other units: largest theta change (stds of the run without the rows)":
                float(change[others].max()),
            "spoiled unit: largest theta change (same)": float(change[~others].max()),
            "noise estimate / clean": ratio.round(3).tolist(),
        }  # fmt: skip
        correct = change.max() < 0.1 and np.all(np.abs(ratio - 1) < 0.1)
        flagged = "outlier" in words or not result.valid[rows].any()
        return Seen(bool(correct), bool(flagged), detail=detail, message=words)

    return run


def _one_wild_value(frame):
    row = frame.index[(frame.unit == 1) & (frame.time == 20)].to_numpy()
    frame.loc[row, "temp"] = 1e6
    return frame, row


def _negative_flows(frame):
    rows = frame.index[(frame.unit == 1) & frame.time.between(10, 14)].to_numpy()
    frame.loc[rows, "inflow"] = -0.5  # the readings of a real flow stay
    return frame, rows


def bad_reading_cases() -> list[Case]:
    k = "one bad reading"
    return [
        Case(k, "1e6 in one row of one unit (UKF, noise estimated)", (),
             _wild("ukf", _one_wild_value)),
        Case(k, "1e6 in one row of one unit (LS, noise estimated)", (),
             _wild("ls", _one_wild_value, window=8)),
        Case(k, "1e6 in one row of one unit (UKF, noise given)", (),
             _wild("ukf", _one_wild_value, estimate=False)),
        Case(k, "five negative-flow operating points (UKF, noise estimated)", (),
             _wild("ukf", _negative_flows)),
    ]  # fmt: skip


# -------------------------------------------------------------------- skipped rows


def _prior_rows(method: str, **options):
    """Unit 0's first three rows outside the model's range: their theta must be the
    prior (the nominal values, inside the bounds), flagged as skipped."""

    def run(ctx: Context) -> Seen:
        frame = ctx.frame.copy()
        rows = frame.index[(frame.unit == 0) & (frame.time < 3)].to_numpy()
        frame.loc[rows, "heat"] = 80.0  # the range is [0, 50]
        result, words = calibrate(ctx.model, frame, method, GIVEN, **options)
        nominal = np.array([p.nominal for p in ctx.model.parameters])
        theta = result.theta[rows]
        return Seen(
            correct=bool(np.allclose(theta, nominal)),
            flagged=not result.valid[rows].any(),
            detail={"theta of the skipped rows": theta.round(4).tolist()},
            message=words,
        )

    return run


def _tiny_noise(std: float):
    def run(ctx: Context) -> Seen:
        tiny = dict.fromkeys(OUTPUTS, std)
        result, words = calibrate(ctx.model, ctx.frame, "ukf", tiny)
        return Seen(
            correct=bool(result.valid.any()),
            flagged="skipped" in words,
            detail={"valid rows": int(result.valid.sum())},
            message=words,
        )

    return run


def _nan_above(w, theta):
    """The tank, NaN where the leak is above 1.5 (inside its box [0.5, 2])."""
    return jnp.where(theta[0] > 1.5, jnp.nan, 1.0) * tank(w, theta)


def _nan_at_low_flow(w, theta):
    """The tank, NaN where the inflow is below 0.8 kg/s."""
    return jnp.where(w[1] < 0.8, jnp.nan, 1.0) * tank(w, theta)


def _nan_box(ctx: Context) -> Seen:
    model = tank_model(_nan_above, name="nan_above")
    result, words = calibrate(model, ctx.frame, "ukf")
    return Seen(correct=False, message=words)


def _nan_rows(ctx: Context) -> Seen:
    model = tank_model(_nan_at_low_flow, name="nan_at_low_flow")
    low = (ctx.frame.inflow < 0.8).to_numpy()
    result, words = calibrate(model, ctx.frame, "ukf", GIVEN)
    return Seen(
        correct=bool(result.valid[~low].all()),
        flagged=not result.valid[low].any(),  # the result's valid / reason
        detail={
            "NaN rows": int(low.sum()),
            "valid": int(result.valid.sum()),
            "named on the console": "finite" in words,
        },
        message=words,
    )


def skipped_cases() -> list[Case]:
    k = "skipped rows"
    return [
        Case(k, "theta of rows skipped before a unit's first used row (UKF)", (),
             _prior_rows("ukf")),
        Case(k, "theta of rows skipped before a unit's first used row (LS)", (),
             _prior_rows("ls", window=8)),
        Case(k, "a noise of 1e-300", ("noise",), _tiny_noise(1e-300)),
        Case(k, "a noise so small that every row is skipped (1e-30)", ("noise",),
             _tiny_noise(1e-30)),
        Case(k, "a model returning NaN in part of the box", ("non-finite",),
             _nan_box),
        Case(k, "a model returning NaN on some rows", (),
             _nan_rows),
    ]  # fmt: skip


# --------------------------------------------------------------------- model files

BAD_FILES = {
    "syntax": "x = 1\ndef broken(:\n    pass\n",
    "raises": "x = 1\nraise RuntimeError('no licence server')\n",
}


def _bad_file(ctx: Context, kind: str) -> Path:
    path = ctx.root / f"bad_{kind}.py"
    if not path.exists():
        path.write_text(BAD_FILES[kind])
        (ctx.root / "tiny.csv").write_text("u,y\n1.0,1.0\n2.0,2.0\n")
    return path


def _file_cli(kind: str, module: str):
    def run(ctx: Context) -> Seen:
        path = _bad_file(ctx, kind)
        args = [f"model={path}:model", f"data={ctx.root / 'tiny.csv'}"]
        if module == "jaxcal.diagnose":
            args += ["calibrate=k", f"out={ctx.root / f'report_{kind}'}"]
        else:
            args += [f"output.runs_dir={ctx.root / 'file_runs'}"]
        proc = ctx.cli(module, *args)
        outcome = classify_cli(proc, (path.name,))
        return Seen(
            correct=False,
            outcome=outcome or "silent wrong",
            detail={"exit code": proc.returncode},
            message=_stderr_excerpt(proc.stderr),
        )

    return run


def _file_python(kind: str):
    def run(ctx: Context) -> Seen:
        jaxcal.models.load(f"{_bad_file(ctx, kind)}:model")
        return Seen(correct=False)

    return run


def file_cases() -> list[Case]:
    k = "model files"
    cases = []
    for kind, what in (("syntax", "a syntax error"), ("raises", "raises at import")):
        name = (f"bad_{kind}.py",)
        cases += [
            Case(k, f"model file with {what}: jaxcal.train", name,
                 _file_cli(kind, "jaxcal.train")),
            Case(k, f"model file with {what}: jaxcal.diagnose", name,
                 _file_cli(kind, "jaxcal.diagnose")),
            Case(k, f"model file with {what}: jaxcal.models.load", name,
                 _file_python(kind)),
        ]  # fmt: skip
    return cases


# ---------------------------------------------------------------------------- runs


def _outside_name(where: str):
    """``name=`` pointing outside ``output.runs_dir``: refused, or where it wrote."""

    def run(ctx: Context) -> Seen:
        assert ctx.toy["run"].exists()  # the toy's files, trained once
        root = ctx.root / f"outside_{where}"
        runs = root / "runs"
        runs.mkdir(parents=True)
        name = "../escaped" if where == "relative" else str(root / "escaped")
        proc = ctx.cli("jaxcal.train", *ctx.toy_argv(name, runs))
        escaped = (root / "escaped").exists()
        outcome = classify_cli(proc, (name,))
        if outcome is None:
            outcome = "silent wrong" if escaped else "correct result"
        return Seen(
            correct=not escaped,
            outcome=outcome,
            detail={"exit code": proc.returncode, "wrote outside runs/": escaped},
            message=_stderr_excerpt(proc.stderr),
        )

    return run


def _twin_trainings(ctx: Context) -> Seen:
    assert ctx.toy["run"].exists()
    runs = ctx.root / "twin_runs"
    argv = [sys.executable, "-m", "jaxcal.train", *ctx.toy_argv("twin", runs)]
    procs = [
        subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=ctx.env(), cwd=ctx.root)
        for _ in range(2)
    ]  # fmt: skip
    outs = [p.communicate(timeout=900) for p in procs]
    codes = sorted(p.returncode for p in procs)
    errs = [o[1] for o in outs]
    metrics = runs / "twin" / "metrics.jsonl"
    steps = []
    if metrics.exists():
        steps = [json.loads(line)["step"] for line in metrics.read_text().splitlines()]
    doubled = len(steps) != len(set(steps))
    detail = {"exit codes": codes, "metrics steps": steps}
    loser = [e for p, e in zip(procs, errs, strict=True) if p.returncode != 0]
    message = _stderr_excerpt(loser[0]) if loser else ""
    if codes == [0, 2] and not doubled:
        named = "twin" in loser[0] and "Traceback" not in loser[0]
        outcome = "clear error" if named else "raw crash"
    elif codes == [0, 0]:
        outcome = "silent wrong"  # two trainings wrote one folder without a word
    else:
        outcome = "raw crash"
    return Seen(correct=False, outcome=outcome, detail=detail, message=message)


def _policy(ctx: Context, model, run=None, data=None):
    toy = ctx.toy
    data = toy["csv"] if data is None else data
    return calibrate(model, data, "policy", run=str(run or toy["run"]))


def _toy_model(ctx: Context):
    return ctx.cached("toy_model", lambda: jaxcal.models.load(
        f"{ctx.toy['file']}:MODEL"))  # fmt: skip


def _toy_before(ctx: Context):
    """The policy's result on the toy data before anything was touched."""
    return ctx.cached("toy_before", lambda: _policy(ctx, _toy_model(ctx))[0])


def _same_xhat(a, b) -> float:
    return float(np.nanmax(np.abs(a.xhat - b.xhat)))


def _edited_file(fresh: bool):
    """The model file edited after training; the model as loaded before the edit
    (``fresh=False``: the run must not follow the file) or after it (``True``: the
    run must refuse a model that is not its own)."""

    def run(ctx: Context) -> Seen:
        before = _toy_before(ctx)
        path = ctx.toy["file"]
        path.write_text(TOY_EDITED)
        try:
            model = jaxcal.models.load(f"{path}:MODEL") if fresh else _toy_model(ctx)
            result, words = _policy(ctx, model)
        finally:
            path.write_text(TOY_SOURCE)
        change = _same_xhat(result, before)
        return Seen(
            correct=bool(change < 1e-9) and not fresh,
            flagged="differ" in words,
            needs_flag=False,
            detail={"largest xhat change": change},
            message=words,
        )

    return run


def _other_model(ctx: Context) -> Seen:
    def other(w, theta):
        return jnp.stack([5 * theta[0] * w[0], theta[1], w[1]])

    model = jaxcal.Model.from_function(
        other,
        conditions={"a": "m", "b": "s"},
        parameters={"p": (1.0, 0.5, 2.0, "-"), "q": (0.5, 0.1, 1.0, "-")},
        outputs=("y1", "y2", "y3"),
        name="other",
    )
    before = _toy_before(ctx)
    result, words = _policy(ctx, model)
    return Seen(
        correct=False,  # the run's policy with the other model's xhat, or ignored
        flagged="'other'" in words,
        detail={"largest xhat change against the run's model": _same_xhat(result,
                                                                          before)},
        message=words,
    )  # fmt: skip


def _moved_file(ctx: Context) -> Seen:
    before = _toy_before(ctx)
    path = ctx.toy["file"]
    moved = path.with_name("moved_model.py")
    path.rename(moved)
    try:
        result, words = _policy(ctx, _toy_model(ctx))
    finally:
        moved.rename(path)
    change = _same_xhat(result, before)
    return Seen(
        correct=bool(change < 1e-9),
        needs_flag=False,
        detail={"largest xhat change": change},
        message=words,
    )


def _outside_import(ctx: Context) -> Seen:
    """A copied run whose data.json names a file outside it, as a run from someone
    else could: loading it must not import that file."""
    import hashlib

    toy = ctx.toy
    copy = ctx.root / "copied_run"
    shutil.copytree(toy["run"], copy)
    marker = ctx.root / "evil_ran"
    evil = ctx.root / "evil.py"
    evil.write_text(
        f"import pathlib\npathlib.Path({str(marker)!r}).write_text('ran')\n"
        + TOY_SOURCE.split('"""', 2)[2]
    )
    data = json.loads((copy / "data.json").read_text())
    data["model_spec"] = f"{evil}:MODEL"
    if "model_source" in data:  # the self-contained layout
        data["model_source"] = {
            "kind": "file",
            "file": os.path.relpath(evil, copy),
            "attr": "MODEL",
            "sha256": hashlib.sha256(evil.read_bytes()).hexdigest(),
        }
    (copy / "data.json").write_text(json.dumps(data))
    try:
        result, words = _policy(ctx, _toy_model(ctx), run=copy)
    except Exception:
        if marker.exists():  # it ran, then failed: the harm is done
            return Seen(correct=False, outcome="silent wrong",
                        detail={"outside file ran": True})  # fmt: skip
        raise
    return Seen(
        correct=not marker.exists(),
        needs_flag=False,
        detail={"outside file ran": marker.exists()},
        message=words,
    )


def run_cases() -> list[Case]:
    k = "runs"
    return [
        Case(k, "name=../x", (), _outside_name("relative")),
        Case(k, "absolute name=", (), _outside_name("absolute")),
        Case(k, "two trainings started together on one name", (), _twin_trainings),
        Case(k, "model file edited after training (model loaded before)", (),
             _edited_file(fresh=False)),
        Case(k, "model file edited after training (the edited model)",
             ("'toy'", "differs"), _edited_file(fresh=True)),
        Case(k, "calibrate(other_model, ..., run=)", ("'other'",), _other_model),
        Case(k, "model file moved after training", ("moved", "toy_model.py"),
             _moved_file),
        Case(k, "data.json naming a file outside the run", ("outside",),
             _outside_import),
    ]  # fmt: skip


# -------------------------------------------------------------------------- memory


def skewed_frame(long: int, short: int, seed: int = 0) -> pd.DataFrame:
    """One unit of ``long`` rows beside ``short`` one-row units."""
    rng = np.random.default_rng(seed)
    n = long + short
    w = np.stack([rng.uniform(5, 30, n), rng.uniform(0.5, 2.0, n)], 1)
    theta = np.tile([1.2, 0.2], (n, 1))
    x = np.asarray(jax.vmap(tank)(w, theta)) + NOISE * rng.standard_normal((n, 3))
    frame = pd.DataFrame({"heat": w[:, 0], "inflow": w[:, 1]})
    for j, name in enumerate(OUTPUTS):
        frame[name] = x[:, j]
    frame["unit"] = np.concatenate([np.zeros(long, np.int64), 1 + np.arange(short)])
    frame["time"] = np.concatenate([np.arange(long), np.zeros(short)])
    return frame


def padded_shapes(data) -> tuple[list[tuple[int, int]], str]:
    """The ``[units, longest]`` of each padded array the front door makes: the
    library's own grouping where it has one, else one array of every unit padded
    to the longest (what ``Dataset.padded`` allocates), computed, not allocated."""
    try:
        from jaxcal.data.buckets import bucket_units
    except ImportError:
        _, counts = np.unique(data.unit, return_counts=True)
        return [(len(counts), int(counts.max()))], "Dataset.padded (computed)"
    parts = bucket_units(data, np.float32).parts
    return [tuple(p.mask.shape) for p in parts], "bucket_units (measured)"


def _memory(ctx: Context) -> Seen:
    frame = skewed_frame(LONG, SHORT)
    data = jaxcal.read_dataset(frame, ctx.model)
    shapes, how = padded_shapes(data)
    cells = sum(u * t for u, t in shapes)
    itemsize = np.dtype(np.float64 if jax.config.jax_enable_x64 else np.float32)
    # per padded cell: w and x in the float dtype, the row index, the mask, and
    # the scan's stacked theta, theta_std and xhat
    per_cell = (2 + 3 + 2 + 2 + 3) * itemsize.itemsize + 8 + 1
    projected = cells * per_cell
    detail = {
        "rows": int(data.num_rows),
        "padded arrays [units, longest]": [list(s) for s in shapes],
        "padded cells / rows": round(cells / data.num_rows, 3),
        "projected bytes (inputs + stacked outputs)": int(projected),
        "how": how,
    }
    if projected > MEMORY_BUDGET:
        detail["not run"] = (
            f"{projected / 1e9:.1f} GB projected for {data.num_rows} rows, above the "
            f"{MEMORY_BUDGET / 1e9:.0f} GB budget (the issue: MemoryError at 9.7 GB)"
        )
        return Seen(correct=False, outcome="raw crash", detail=detail,
                    message=detail["not run"])  # fmt: skip
    proc = subprocess.run(
        [sys.executable, os.path.abspath(__file__), "child=memory"],
        capture_output=True, text=True, env=ctx.env(), timeout=1800, check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        return Seen(correct=False, outcome="raw crash", detail=detail,
                    message=_stderr_excerpt(proc.stderr))  # fmt: skip
    child = json.loads(proc.stdout.strip().splitlines()[-1])
    detail.update(child)
    ok = child["valid share"] == 1.0 and child["finite"] and child["theta error"] < 0.05
    return Seen(correct=bool(ok), needs_flag=False, detail=detail)


def memory_child() -> None:
    """The memory case's calibration, in a process of its own (peak RSS)."""
    start = time.perf_counter()
    frame = skewed_frame(LONG, SHORT)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxcal.calibrate(tank_model(), frame, "ukf", noise=GIVEN)
    last = result.theta[result.unit == 0][-1]
    print(json.dumps({
        "seconds": round(time.perf_counter() - start, 1),
        "peak RSS (GB)": round(
            resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 2),
        "valid share": float(result.valid.mean()),
        "finite": bool(np.isfinite(result.theta).all()),
        "theta error": float(np.max(np.abs(last - np.array([1.2, 0.2])))),
    }))  # fmt: skip


def memory_cases() -> list[Case]:
    return [
        Case("memory", f"one unit of {LONG:,} rows beside {SHORT:,} one-row units",
             (), _memory),
    ]  # fmt: skip


# ------------------------------------------------------------ partial observations


def _partial(method: str, **options):
    """Three rows of unit 1 with ``temp`` missing: used, and flagged ``partial``."""

    def run(ctx: Context) -> Seen:
        frame = ctx.frame.copy()
        rows = frame.index[(frame.unit == 1) & frame.time.isin([10, 11, 12])]
        frame.loc[rows, "temp"] = np.nan
        result, words = calibrate(ctx.model, frame, method, GIVEN, **options)
        partial = getattr(result, "partial", None)
        rows = rows.to_numpy()
        used = bool(result.valid[rows].all() and np.isfinite(result.theta).all())
        return Seen(
            correct=used,
            flagged=partial is not None and bool(partial[rows].all()),
            detail={"used": used, "reason": sorted(set(result.reason[rows]))},
            message=words,
        )

    return run


def _partial_policy(ctx: Context) -> Seen:
    """A policy cannot take a NaN: the row is skipped as ``x_partial`` and said."""
    frame = pd.read_csv(ctx.toy["csv"])
    row = int(np.flatnonzero((frame.unit == 2) & (frame.time == 10))[0])
    frame.loc[row, "y2"] = np.nan
    result, words = _policy(ctx, _toy_model(ctx), data=frame)
    partial = getattr(result, "partial", None)
    others = np.delete(np.arange(len(frame)), row)
    return Seen(
        correct=bool(result.valid[others].all()),
        flagged=partial is not None and bool(partial[row]),
        detail={"reason": str(result.reason[row])},
        message=words,
    )


def partial_cases() -> list[Case]:
    k = "partial observations"
    rows = ("row", "temp")
    return [
        Case(k, "a row with one output NaN (UKF)", rows, _partial("ukf")),
        Case(k, "a row with one output NaN (LS)", rows, _partial("ls", window=8)),
        Case(k, "a row with one output NaN (policy)", ("row", "y2"), _partial_policy),
    ]


# ------------------------------------------------------------------ issue 42 cases
# Issue 42 lists more hostile inputs, by class; they are probed by ``issue=42`` into
# ``<label>_issue42.json`` and tabled beside issue 25's.

CLASSES_42 = (
    "user functions",
    "options",
    "files",
    "warnings",
    "globals",
    "bounds",
    "screening",
    "security",
)
TESTS_42 = {
    "user functions": ["tests/calibrators/test_hostile_functions.py",
                       "tests/test_model_contract.py"],
    "options": ["tests/calibrators/test_hostile_functions.py"],
    "files": ["tests/data/test_hostile_files.py"],
    "warnings": ["tests/test_trust.py"],
    "globals": ["tests/calibrators/test_hostile_functions.py"],
    "bounds": ["tests/calibrators/test_hostile_functions.py"],
    "screening": ["tests/calibrators/test_hostile_screening.py"],
    "security": ["tests/test_trust.py"],
}  # fmt: skip
USER = ("'user'",)  # a clear error about a user's function names its model


def _user_fn_case(make_model):
    """A user function jaxcal cannot trace, or not a function at all: only an error
    naming the model (or the argument) is right."""

    def run(ctx: Context) -> Seen:
        model = make_model()
        result, words = calibrate(model, ctx.frame, "ukf", GIVEN)
        return Seen(correct=False, message=words)

    return run


def _numpy_on_tracer(w, theta):
    return jnp.asarray(np.exp(np.asarray(theta))) * tank(w, theta)


def _if_on_theta(w, theta):
    if theta[0] > 1.0:
        return tank(w, theta)
    return 2.0 * tank(w, theta)


def _float_theta(w, theta):
    return float(theta[0]) * tank(w, theta) / float(theta[0])


def _callback(w, theta):
    out = jax.ShapeDtypeStruct((3,), w.dtype)
    host = lambda a, b: np.asarray(tank(a, b), a.dtype)  # noqa: E731
    return jax.pure_callback(host, out, w, theta)


def _callback_case(ctx: Context) -> Seen:
    """``pure_callback`` without ``vmap_method``: a correct result (the callback
    run row by row) or an error naming the model and the fix."""
    model = tank_model(_callback, name="user")
    result, words = calibrate(model, ctx.frame, "ukf", GIVEN)
    change = _close(result, ctx.reference)
    return Seen(correct=bool(change < 0.1), needs_flag=False, message=words,
                detail={"largest theta change (ref stds)": change})  # fmt: skip


def user_function_cases() -> list[Case]:
    k = "user functions"
    return [
        Case(k, "numpy called on a traced theta", USER,
             _user_fn_case(lambda: tank_model(_numpy_on_tracer, name="user"))),
        Case(k, "a Python if on theta", USER,
             _user_fn_case(lambda: tank_model(_if_on_theta, name="user"))),
        Case(k, "float(theta)", USER,
             _user_fn_case(lambda: tank_model(_float_theta, name="user"))),
        Case(k, "jax.pure_callback without vmap_method", USER, _callback_case),
        Case(k, "fn(w) of one argument", USER + ("fn(w, theta)",),
             _user_fn_case(lambda: tank_model(lambda w: tank(w, w), name="user"))),
        Case(k, "a string instead of a function", ("callable", "'tank'"),
             _user_fn_case(lambda: tank_model("tank", name="user"))),
    ]  # fmt: skip


def _option_case(method: str, names=None, **options):
    """An option of the wrong type or value: only an error naming it is right (a
    result computed with it, or with a guess of what was meant, is not)."""

    def run(ctx: Context) -> Seen:
        if names is not None:
            result, words = calibrate(ctx.model, ctx.frame, method, GIVEN,
                                      theta=names, **options)  # fmt: skip
            detail = {"parameters calibrated": list(result.theta_names)}
        else:
            result, words = calibrate(ctx.model, ctx.frame, method, GIVEN, **options)
            detail = {"finite theta": bool(np.isfinite(result.theta).all())}
        return Seen(correct=False, message=words, detail=detail)

    return run


def option_cases() -> list[Case]:
    k = "options"
    q = ("q=", "'q'", "option q", "q must")
    return [
        Case(k, "q=inf (UKF)", q, _option_case("ukf", q=float("inf"))),
        Case(k, "q='0.01', a string (UKF)", q, _option_case("ukf", q="0.01")),
        Case(k, "window=8.5, a float (LS)", ("window",),
             _option_case("ls", window=8.5)),
        Case(k, "theta=[] (UKF)", ("theta",), _option_case("ukf", names=[])),
    ]  # fmt: skip


def _european_csv(ctx: Context) -> Seen:
    """A CSV saved in a European locale: ';' between fields, ',' as the decimal
    mark. Read as the same numbers (same result) or an error saying so."""
    path = ctx.root / "european.csv"
    ctx.frame.to_csv(path, index=False, sep=";", decimal=",")
    result, words = calibrate(ctx.model, path, "ukf", GIVEN)
    change = _close(result, ctx.reference)
    return Seen(correct=bool(change < 1e-3), needs_flag=False, message=words,
                detail={"largest theta change (ref stds)": change})  # fmt: skip


def _huge_units(ctx: Context) -> Seen:
    """Three units whose ids are beyond int64 (2**63 + k): kept apart, or an error
    naming the column and rows."""
    frame = ctx.frame.copy()
    path = ctx.root / "huge_units.csv"
    text = frame.assign(unit=[str(2**63 + int(u)) for u in frame.unit]).to_csv(
        index=False
    )
    path.write_text(text)
    result, words = calibrate(ctx.model, path, "ukf", GIVEN)
    read = sorted({str(u) for u in np.asarray(result.unit).tolist()})
    written = sorted({str(2**63 + int(u)) for u in frame.unit})
    return Seen(correct=read == written, needs_flag=False, message=words,
                detail={"unit ids read": read})  # fmt: skip


def _tampered_result(ctx: Context) -> Seen:
    """A saved result whose stored dtype of theta was edited to int8: read back
    as the floats saved, or refused naming the field."""
    import pyarrow.parquet as pq

    from jaxcal.calibrators.front.result import META_KEY, CalibrationResult

    path = ctx.reference.save(ctx.root / "tampered.parquet")
    table = pq.read_table(path)
    meta = json.loads(table.schema.metadata[META_KEY])
    meta["dtypes"]["theta"] = "int8"
    table = table.replace_schema_metadata({META_KEY: json.dumps(meta).encode()})
    pq.write_table(table, path)
    loaded = CalibrationResult.load(path)
    same = np.array_equal(loaded.theta, ctx.reference.theta)
    return Seen(correct=bool(same), needs_flag=False,
                detail={"theta dtype read": str(loaded.theta.dtype)})  # fmt: skip


def _truncated_checkpoint(ctx: Context) -> Seen:
    """A copied run whose policy checkpoints were cut short (the largest file of
    every saved step, ``policy/`` and ``policy_best/``, cut in half): a result
    from them, or an error not naming the damage, is not right."""
    copy = ctx.root / "truncated_run"
    shutil.copytree(ctx.toy["run"], copy)
    cut = []
    for step in [*copy.glob("policy/*"), *copy.glob("policy_best/*")]:
        files = [p for p in step.rglob("*") if p.is_file()]
        if step.is_dir() and files:
            biggest = max(files, key=lambda p: p.stat().st_size)
            data = biggest.read_bytes()
            biggest.write_bytes(data[: len(data) // 2])
            cut.append(str(biggest.relative_to(copy)))
    result, words = _policy(ctx, _toy_model(ctx), run=copy)
    return Seen(correct=False, message=words, detail={"files cut": cut})


def _out_path(kind: str):
    """``jaxcal.fleet out=`` that cannot be written: a path under a file, or a
    folder. A clear error before the work (exit 2, naming out=), not a traceback
    after it."""

    def run(ctx: Context) -> Seen:
        toy = ctx.toy
        a_file = ctx.root / "a_file"
        a_file.write_text("not a folder")
        out = a_file / "out.h5" if kind == "under a file" else ctx.root
        proc = ctx.cli(
            "jaxcal.fleet", f"model={toy['file']}:MODEL", f"data={toy['csv']}",
            "method=ukf", "noise=0.01", f"out={out}",
        )  # fmt: skip
        outcome = classify_cli(proc, ("out=",)) or "silent wrong"
        return Seen(correct=False, outcome=outcome, message=_stderr_excerpt(
            proc.stderr), detail={"exit code": proc.returncode})  # fmt: skip

    return run


def _save_path(kind: str):
    """``result.save(path)`` where ``path`` is a folder, or under a file."""

    def run(ctx: Context) -> Seen:
        a_file = ctx.root / "b_file"
        a_file.write_text("not a folder")
        path = ctx.root if kind == "a folder" else a_file / "r.parquet"
        ctx.reference.save(path)
        return Seen(correct=False)

    return run


def _read_only(ctx: Context) -> Seen:
    """``result.save`` into a read-only folder: refused naming it, or (as root,
    who may write anywhere) written."""
    folder = ctx.root / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        path = ctx.reference.save(folder / "r.parquet")
        written = Path(path).is_file()
    finally:
        folder.chmod(0o755)
    return Seen(correct=written, needs_flag=False,
                detail={"written (root may)": written,
                        "uid": os.getuid()})  # fmt: skip


def file_cases_42() -> list[Case]:
    k = "files"
    return [
        Case(k, "a ';' CSV with decimal commas", ("european.csv",), _european_csv),
        Case(k, "unit ids beyond int64", ("'unit'",), _huge_units),
        Case(k, "a result file whose theta dtype was edited", ("'theta'",),
             _tampered_result),
        Case(k, "a truncated policy checkpoint", ("truncated", "corrupt"),
             _truncated_checkpoint),
        Case(k, "jaxcal.fleet out= under a file", (), _out_path("under a file")),
        Case(k, "jaxcal.fleet out= naming a folder", (), _out_path("a folder")),
        Case(k, "result.save(path) naming a folder", ("folder",),
             _save_path("a folder")),
        Case(k, "result.save(path) under a file", ("b_file",),
             _save_path("under a file")),
        Case(k, "result.save(path) in a read-only folder", ("read_only",),
             _read_only),
    ]  # fmt: skip


CHILD_CALIBRATE = """
import json, sys, warnings
sys.path.insert(0, {here!r})
import numpy as np
import hostile_probe as hp
import jaxcal
{setup}
frame = hp.tank_frame()
result = jaxcal.calibrate(hp.tank_model(), frame, "ukf", noise=hp.GIVEN,
                          progress=False)
print(json.dumps({{"theta": result.theta[-1].tolist()}}))
"""


def _child(ctx: Context, code: str, env: dict | None = None, flags=(), cwd=None):
    return subprocess.run(
        [sys.executable, *flags, "-c", code], capture_output=True, text=True,
        env={**ctx.env(), **(env or {})}, cwd=cwd or ctx.root, timeout=900,
        check=False,
    )  # fmt: skip


def _deprecation(ctx: Context) -> Seen:
    """A clean call under ``-W error::DeprecationWarning`` (with the on-disk cache
    on, a fresh one): it must run."""
    code = CHILD_CALIBRATE.format(here=os.path.dirname(__file__), setup="")
    env = {"JAXCAL_CACHE_DIR": str(ctx.root / "dep_cache" / "xla"),
           "JAXCAL_CACHE": "1"}  # fmt: skip
    proc = _child(ctx, code, env, flags=("-W", "error::DeprecationWarning"))
    ok = proc.returncode == 0
    return Seen(correct=ok, needs_flag=False, outcome=None if ok else "raw crash",
                message="" if ok else _stderr_excerpt(proc.stderr),
                detail={"exit code": proc.returncode})  # fmt: skip


GAIN = {"value": 1.0}


def _gained(w, theta):
    """The tank with every output times a gain read from a global."""
    return GAIN["value"] * tank(w, theta)


def _changing_global(ctx: Context) -> Seen:
    """A function reading a global that changes between two calls: the second call
    must use the new value (as a fresh function with it does), or refuse."""
    model = tank_model(_gained, name="user")
    GAIN["value"] = 1.0
    calibrate(model, ctx.frame, "ukf", GIVEN)
    frame = ctx.frame.copy()
    for name in OUTPUTS:
        frame[name] = 1.5 * frame[name]
    GAIN["value"] = 1.5
    try:
        result, words = calibrate(model, frame, "ukf", GIVEN)
        fresh = tank_model(lambda w, t: 1.5 * tank(w, t), name="fresh")
        reference, _ = calibrate(fresh, frame, "ukf", GIVEN)
    finally:
        GAIN["value"] = 1.0
    change = _close(result, reference)
    return Seen(correct=bool(change < 0.1), needs_flag=False, message=words,
                detail={"largest theta change against a fresh function (its "
                        "stds)": change})  # fmt: skip


def _infinite_at_bound(w, theta):
    """The tank whose level is infinite at the leak's lower bound (0.5)."""
    heat, inflow = w[0], w[1]
    leak, loss = theta[0], theta[1]
    level = inflow / (leak - 0.5)
    temp = 20.0 + heat / (inflow * (1.0 + loss))
    return jnp.stack([level, temp, leak * inflow * (1.0 - 0.1 * loss)])


def _bound_case(method: str, **options):
    """Data whose true leak (0.55) is near the bound where an output is infinite:
    theta must stay inside the box (a row at the bound flagged)."""

    def run(ctx: Context) -> Seen:
        model = tank_model(_infinite_at_bound, name="user")
        rng = np.random.default_rng(3)
        frame = ctx.frame.copy()
        theta = np.tile([0.55, 0.2], (len(frame), 1))
        x = np.asarray(jax.vmap(_infinite_at_bound)(
            frame[["heat", "inflow"]].to_numpy(), theta))  # fmt: skip
        x = x + NOISE * rng.standard_normal(x.shape)
        for j, name in enumerate(OUTPUTS):
            frame[name] = x[:, j]
        result, words = calibrate(model, frame, method, GIVEN, **options)
        low = np.array([p.low for p in model.parameters])
        high = np.array([p.high for p in model.parameters])
        inside = bool(
            np.all(np.isfinite(result.theta))
            and np.all((result.theta >= low) & (result.theta <= high))
        )
        return Seen(
            correct=inside,
            flagged="bound" in words.lower() or not result.valid.all(),
            message=words,
            detail={
                "theta range": [
                    np.nanmin(result.theta, 0).tolist(),
                    np.nanmax(result.theta, 0).tolist(),
                ]
            },
        )

    return run  # fmt: skip


def _stuck_sensor(ctx: Context) -> Seen:
    """Unit 1's outflow stuck at one value from time 10 on: the other outputs'
    rows must not be dropped as outliers, and the stuck output must be said."""
    model = ctx.cached("open", lambda: tank_model(name="open", box=False))
    frame = ctx.cached("frame4", lambda: tank_frame(num_units=4)).copy()
    rows = frame.index[(frame.unit == 1) & (frame.time >= 10)].to_numpy()
    frame.loc[rows, "outflow"] = frame.loc[rows[0], "outflow"]
    result, words = calibrate(model, frame, "ukf")
    dropped = int((result.reason[rows] == "outlier").sum())
    flagged = "outflow" in words and ("stuck" in words or "constant" in words)
    return Seen(
        correct=dropped == 0,
        flagged=flagged,
        message=words,
        detail={"rows of the good outputs dropped as outliers": dropped},
    )


def _three_rows(ctx: Context) -> Seen:
    """The noise estimated from three rows: refused (naming noise=) or flagged in
    the result's notes; a result without a word is silent."""
    frame = tank_frame(num_units=1, length=3)
    result, words = calibrate(ctx.model, frame, "ukf")
    ratio = np.asarray(result.problem.noise_std) / NOISE
    flagged = "noise=" in words and "rows" in words
    return Seen(
        correct=flagged,
        flagged=flagged,
        message=words,
        detail={"noise estimate / true": ratio.round(2).tolist()},
    )


def screening_cases() -> list[Case]:
    k = "screening"
    return [
        Case(k, "a stuck sensor (unit 1's outflow constant from time 10)", (),
             _stuck_sensor),
        Case(k, "the noise estimated from three rows", ("noise=",), _three_rows),
    ]  # fmt: skip


PLANT = """
import sys, pathlib
import jax, jax.numpy as jnp
from jax import export
import jaxcal.calibrators.programs.on_disk  # registers the programs' named tuples
folder = pathlib.Path(sys.argv[1])
for path in folder.rglob("*.jaxexport"):
    exp = export.deserialize(bytearray(path.read_bytes()))
    args, kwargs = jax.tree.unflatten(exp.in_tree, exp.in_avals)
    def planted(*a, **k):
        out = exp.call(*a, **k)
        return jax.tree.map(lambda o: o + 0.25 if jnp.issubdtype(o.dtype,
                            jnp.floating) else o, out)
    new = export.export(jax.jit(planted))(*args, **kwargs)
    path.write_bytes(bytes(new.serialize()))
    print("planted", path.name)
"""


def _planted_cache(ctx: Context) -> Seen:
    """A world-writable ``JAXCAL_CACHE_DIR`` whose stored programs another user
    rewrote to add 0.25 to every output: the next call must not use them (the
    same theta as before the planting; a warning naming the folder)."""
    cache = ctx.root / "shared_cache"
    (cache / "xla").mkdir(parents=True)
    for folder in (cache, cache / "xla"):
        folder.chmod(0o777)
    env = {"JAXCAL_CACHE_DIR": str(cache / "xla"), "JAXCAL_CACHE": "1"}
    code = CHILD_CALIBRATE.format(here=os.path.dirname(__file__), setup="")
    first = _child(ctx, code, env)
    if first.returncode != 0:
        return Seen(correct=False, outcome="raw crash",
                    message=_stderr_excerpt(first.stderr))  # fmt: skip
    plant = subprocess.run(
        [sys.executable, "-c", PLANT, str(cache)], capture_output=True, text=True,
        env={**ctx.env(), **env}, timeout=900, check=False,
    )  # fmt: skip
    planted = plant.stdout.count("planted")
    second = _child(ctx, code, env)
    if second.returncode != 0:
        outcome = "clear error" if "shared_cache" in second.stderr else "raw crash"
        return Seen(correct=False, outcome=outcome,
                    message=_stderr_excerpt(second.stderr))  # fmt: skip
    before = json.loads(first.stdout.strip().splitlines()[-1])["theta"]
    after = json.loads(second.stdout.strip().splitlines()[-1])["theta"]
    change = float(np.max(np.abs(np.subtract(after, before))))
    warned = "shared_cache" in second.stderr or "writable" in second.stderr
    return Seen(correct=change < 1e-6, flagged=warned,
                message=_stderr_excerpt(second.stderr) if warned else "",
                detail={"programs planted": planted,
                        "largest theta change": change})  # fmt: skip


def _edit_source(copy: Path, record: dict) -> None:
    data = json.loads((copy / "data.json").read_text())
    data["model_source"] = record
    (copy / "data.json").write_text(json.dumps(data))


def _load_run_child(ctx: Context, run: Path, cwd: Path, marker: Path):
    """``StreamingCalibrator(run)`` in a fresh process started in ``cwd`` (as a
    user would, ``python`` there): the outcome by the marker and the exit."""
    code = (
        "from jaxcal.deploy.streaming import StreamingCalibrator\n"
        f"StreamingCalibrator({str(run)!r})\n"
    )
    proc = _child(ctx, code, cwd=cwd)
    ran = marker.exists()
    if ran:
        return Seen(correct=False, outcome="silent wrong",
                    detail={"outside code ran": True})  # fmt: skip
    if proc.returncode == 0:
        return Seen(correct=True, needs_flag=False, detail={"outside code ran": False})
    last = [line for line in proc.stderr.splitlines() if line.strip()][-1:]
    frames = [line for line in proc.stderr.splitlines() if 'File "' in line]
    ours = bool(frames) and LIBRARY in frames[-1]
    named = any(w in proc.stderr for w in ("trust_code", "module", "outside"))
    kind = bool(last) and (last[0].startswith("ValueError") or "jaxcal" in last[0])
    outcome = "clear error" if (ours and named and kind) else "raw crash"
    return Seen(correct=False, outcome=outcome, message=_stderr_excerpt(proc.stderr),
                detail={"outside code ran": False})  # fmt: skip


def _module_from_cwd(ctx: Context) -> Seen:
    """A run whose data.json names a model module ``evil_mod`` that sits in the
    working directory, not in the run: loading it must not import it."""
    copy = ctx.root / "module_run"
    shutil.copytree(ctx.toy["run"], copy)
    cwd = ctx.root / "work_dir"
    cwd.mkdir()
    marker = ctx.root / "evil_mod_ran"
    (cwd / "evil_mod.py").write_text(
        f"import pathlib\npathlib.Path({str(marker)!r}).write_text('ran')\n"
        + TOY_SOURCE.split('"""', 2)[2]
    )
    _edit_source(copy, {"kind": "module", "module": "evil_mod", "attr": "MODEL",
                        "sha256": None})  # fmt: skip
    return _load_run_child(ctx, copy, cwd, marker)


def _os_getpid(ctx: Context) -> Seen:
    """A run whose data.json names ``os:getpid`` as its model: the callable must not
    be called."""
    copy = ctx.root / "getpid_run"
    shutil.copytree(ctx.toy["run"], copy)
    _edit_source(copy, {"kind": "module", "module": "os", "attr": "getpid",
                        "sha256": None})  # fmt: skip
    calls = []
    real = os.getpid

    def counted():
        calls.append(1)
        return real()

    from jaxcal.deploy.streaming import StreamingCalibrator

    os.getpid = counted
    try:
        StreamingCalibrator(str(copy))
    except Exception as err:
        if calls:
            return Seen(correct=False, outcome="silent wrong",
                        message=_excerpt(f"{type(err).__name__}: {err}"),
                        detail={"os.getpid called": len(calls)})  # fmt: skip
        raise
    finally:
        os.getpid = real
    return Seen(correct=not calls, needs_flag=False,
                detail={"os.getpid called": len(calls)})  # fmt: skip


def _received_run(ctx: Context) -> Seen:
    """A run received from someone else whose model/ copy (and its digest in
    data.json) was rewritten: loading it must not run the copy without consent."""
    import hashlib

    copy = ctx.root / "received_run"
    shutil.copytree(ctx.toy["run"], copy)
    data = json.loads((copy / "data.json").read_text())
    record = data.get("model_source") or {}
    marker = ctx.root / "received_copy_ran"
    if record.get("kind") != "file":
        return Seen(correct=False, outcome="raw crash",
                    message=f"no model copy in the run: {record}")  # fmt: skip
    path = copy / record["file"]
    text = (f"import pathlib\npathlib.Path({str(marker)!r}).write_text('ran')\n"
            + TOY_SOURCE.split('"""', 2)[2])  # fmt: skip
    path.write_text(text)
    record["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    _edit_source(copy, record)
    return _load_run_child(ctx, copy, ctx.root, marker)


def _json_base(ctx: Context) -> Seen:
    """An extended-model JSON whose base is a .py file elsewhere: loading the JSON
    must not run that file without consent."""
    from jaxcal.models.extended import FORMAT

    elsewhere = ctx.root / "elsewhere"
    elsewhere.mkdir()
    marker = ctx.root / "json_base_ran"
    (elsewhere / "base.py").write_text(
        f"import pathlib\npathlib.Path({str(marker)!r}).write_text('ran')\n"
        + TOY_SOURCE.split('"""', 2)[2]
    )
    specs = ctx.root / "specs"
    specs.mkdir()
    spec = {"format": FORMAT, "base": "../elsewhere/base.py:MODEL",
            "declared": ["p", "q"], "added": []}  # fmt: skip
    (specs / "ext.json").write_text(json.dumps(spec))
    try:
        jaxcal.models.load(str(specs / "ext.json"))
    except Exception as err:
        if marker.exists():
            return Seen(correct=False, outcome="silent wrong",
                        message=_excerpt(f"{type(err).__name__}: {err}"),
                        detail={"base file ran": True})  # fmt: skip
        raise
    ran = marker.exists()
    return Seen(correct=not ran, needs_flag=False, detail={"base file ran": ran})


def security_cases() -> list[Case]:
    k = "security"
    consent = ("trust_code",)
    return [
        Case(k, "a world-writable JAXCAL_CACHE_DIR with planted programs", (),
             _planted_cache),
        Case(k, "data.json model source 'module' naming a module in the cwd", (),
             _module_from_cwd),
        Case(k, "data.json model source 'os:getpid'", ("os", "getpid", "module"),
             _os_getpid),
        Case(k, "a received run's model/ copy (digest rewritten too)", (),
             _received_run),
        Case(k, "a JSON spec whose base is a .py elsewhere", consent + ("base.py",),
             _json_base),
    ]  # fmt: skip


def issue42_cases() -> list[Case]:
    return [
        *user_function_cases(),
        *option_cases(),
        *file_cases_42(),
        Case("warnings", "a clean call under -W error::DeprecationWarning", (),
             _deprecation),
        Case("globals", "fn reads a global that changes between calls", USER,
             _changing_global),
        Case("bounds", "an output infinite at a bound (UKF)", (),
             _bound_case("ukf")),
        Case("bounds", "an output infinite at a bound (LS)", (),
             _bound_case("ls", window=8)),
        *screening_cases(),
        *security_cases(),
    ]  # fmt: skip


# ---------------------------------------------------------------------------- main


def all_cases() -> list[Case]:
    return [
        *contract_cases(),
        *table_cases(),
        *bad_reading_cases(),
        *skipped_cases(),
        *file_cases(),
        *run_cases(),
        *memory_cases(),
        *partial_cases(),
    ]


def run_one(case: Case, ctx: Context) -> dict:
    start = time.perf_counter()
    detail: dict = {}
    try:
        seen = case.run(ctx)
    except Exception as err:  # noqa: BLE001 - every failure is a finding
        outcome, message = classify_error(err, case.names)
    else:
        outcome, message, detail = classify_seen(seen), seen.message, seen.detail
    return {
        "class": case.klass,
        "case": case.name,
        "outcome": outcome,
        "message": _excerpt(message),
        "detail": _jsonable(detail),
        "seconds": round(time.perf_counter() - start, 1),
    }


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.generic,)):
        return value.item()
    return value


def _commit() -> str:
    """The probed tree's commit, ``+changes`` when its jaxcal/ has uncommitted
    edits."""
    top = os.path.dirname(LIBRARY)
    head = subprocess.run(
        ["git", "-C", top, "rev-parse", "--short", "HEAD"],
        capture_output=True, text=True, check=False,
    ).stdout.strip()  # fmt: skip
    dirty = subprocess.run(
        ["git", "-C", top, "status", "--porcelain", "--", "jaxcal"],
        capture_output=True, text=True, check=False,
    ).stdout.strip()  # fmt: skip
    return (head or "unknown") + ("+changes" if dirty else "")


def probe(out: Path, label: str, only: str | None, issue: str = "25") -> None:
    """Run the cases of ``issue`` (25: :func:`all_cases`, 42:
    :func:`issue42_cases`) and write ``<out>/<label>[_issue42].json``."""
    out.mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix=f"hostile_{label}_"))
    ctx = Context(root)
    records = []
    cases, classes = (
        (issue42_cases(), CLASSES_42) if issue == "42" else (all_cases(), CLASSES)
    )
    try:
        for case in cases:
            if only and only not in case.name and only != case.klass:
                continue
            record = run_one(case, ctx)
            records.append(record)
            print(f"[{record['outcome']:>14}] {case.klass}: {case.name} "
                  f"({record['seconds']} s) {record['message'][:120]}",
                  flush=True)  # fmt: skip
    finally:
        shutil.rmtree(root, ignore_errors=True)
    counts = {
        k: {o: sum(r["outcome"] == o for r in records if r["class"] == k)
            for o in OUTCOMES}
        for k in classes
    }  # fmt: skip
    report = {
        "label": label,
        "library": LIBRARY,
        "commit": _commit(),
        "command": " ".join([os.path.relpath(__file__), *sys.argv[1:]]),
        "counts": counts,
        "cases": records,
    }
    name = f"{label}_issue42.json" if issue == "42" else f"{label}.json"
    if only and (out / name).exists():  # a re-run of some cases: merged in
        kept = json.loads((out / name).read_text())
        new = {(r["class"], r["case"]): r for r in records}
        records = [new.pop((r["class"], r["case"]), r) for r in kept["cases"]]
        records += list(new.values())
        report["cases"] = records
        report["counts"] = {
            k: {o: sum(r["outcome"] == o for r in records if r["class"] == k)
                for o in OUTCOMES}
            for k in classes
        }  # fmt: skip
        report["command"] = kept["command"] + " ; " + report["command"]
    (out / name).write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {out / name}")


# -------------------------------------------------------------------------- report

SHORT_NAMES = {
    "clear error": "error",
    "flagged result": "flagged",
    "correct result": "correct",
    "silent wrong": "SILENT WRONG",
    "raw crash": "RAW CRASH",
}


README_HEAD = """# Hostile input at the front door: before and after issue 25

Written by `experiments/hostile_probe.py`; every count and message below comes from
`before.json` and `after.json`, which the same script wrote on each tree:

```bash
git worktree add /tmp/before 74da562
(cd /tmp/before && JAX_PLATFORMS=cpu PYTHONPATH=/tmp/before \\
  /work/main/.venv/bin/python /work/main/experiments/hostile_probe.py \\
  out=/work/main/results/hostile label=before)
JAX_PLATFORMS=cpu .venv/bin/python experiments/hostile_probe.py \\
  out=results/hostile label=after
.venv/bin/python experiments/hostile_probe.py report=results/hostile
```

Before: {before} (jaxcal from `{before_lib}`); after: {after} (`+changes`: the
working tree, with uncommitted edits under jaxcal/). Each case runs a
tiny tank model (float32, as `jaxcal.calibrate` runs without x64) or a toy policy
trained with `preset=smoke`. Outcomes, by the rules of the script's docstring:
**error** a clear error (a `ValueError` raised by jaxcal whose message names the
field, file, row or name involved; on a command line exit 2, one line, no
traceback), **flagged** a correct result with the flag the case needs (a console
warning or the result's `valid` / `reason` / `partial`), **correct** a correct
result where nothing needed a flag, **SILENT WRONG** a wrong result or one missing
its flag, **RAW CRASH** any other exception (raised inside JAX, numpy, pandas or
Python, or a message not naming the user's thing) or another exit code.

| class | cases | before | after | test (file::test) |
|---|---|---|---|---|
"""

README_NOTES = """
Reading the numbers:

- The old code is driven through the API it had: no case passes an argument it
  lacked (`result.partial` is read only where it exists). Where the old API
  refused something outright, the case records what its user got: a NaN output
  cell was refused by the old reader, naming the row (a clear error by the rules;
  the new code uses the row in the UKF and least squares, skips it as `x_partial`
  in a policy and marks it in `result.partial`); a run whose model file moved
  failed with an error naming the file (a run now keeps a copy of its model).
- The memory case is not run where the padded arrays would take more than
  {budget:.0f} GB: the old code's `[units, longest]` shape is computed as
  `Dataset.padded` would allocate it and counted as a raw crash (the issue measured
  a MemoryError at 9.7 GB). On the new code the calibration runs in a child process
  and its peak RSS is recorded in `after.json`.
- Two trainings started together on one name race: on the old code which of them
  fails, and how (interleaved metrics with both exiting 0, or an exception in one),
  depends on timing, so a rerun may move that case between silent wrong and raw
  crash; on the new code the lock decides (exit 2 for the second).
- One bad reading: correct means every stream, the spoiled unit's other rows
  included, within 0.1 std of the calibration without the spoiled rows and the
  noise estimate within 10 % of the clean one; the measured changes are in the
  JSON files.
"""


def _cell(record: dict, size: int = 110) -> str:
    """A record's message, or what was measured where there was none (a result
    without a word), for a table cell."""
    text = record.get("message", "")
    if not text and record.get("detail"):
        text = "; ".join(f"{k}: {_short(v)}" for k, v in record["detail"].items())
    return _excerpt(text, size).replace("|", "/") or " "


def _short(value):
    """Floats to 3 significant digits (in lists too) for a table cell."""
    if isinstance(value, float):
        return f"{value:.3g}"
    if isinstance(value, list):
        return "[" + ", ".join(str(_short(v)) for v in value) + "]"
    return value


def _counts_cell(counts: dict) -> str:
    return ", ".join(f"{SHORT_NAMES[o]} {n}" for o, n in counts.items() if n) or "-"


def _tables(before: dict, after: dict, classes, tests: dict) -> list[str]:
    """The class table (counts before and after, the tests) and every case."""
    lines = [
        "| class | cases | before | after | test (file::test) |",
        "|---|---|---|---|---|",
    ]
    for klass in classes:
        n = sum(r["class"] == klass for r in after["cases"])
        held = "<br>".join(f"`{t}`" for t in tests[klass])
        lines.append(
            f"| {klass} | {n} | {_counts_cell(before['counts'][klass])} | "
            f"{_counts_cell(after['counts'][klass])} | {held} |"
        )
    total = {
        label: {o: sum(r["outcome"] == o for r in run["cases"]) for o in OUTCOMES}
        for label, run in (("before", before), ("after", after))
    }
    lines.append(
        f"| **all** | {len(after['cases'])} | {_counts_cell(total['before'])} | "
        f"{_counts_cell(total['after'])} | |"
    )
    lines += [
        "",
        "| class | case | before | what it gave | after | what it gives |",
        "|---|---|---|---|---|---|",
    ]
    old = {(r["class"], r["case"]): r for r in before["cases"]}
    for r in after["cases"]:
        b = old.get((r["class"], r["case"]), {"outcome": "-"})
        lines.append(
            f"| {r['class']} | {r['case']} | {b['outcome']} | {_cell(b)} "
            f"| {r['outcome']} | {_cell(r)} |"
        )
    return lines


def write_report(folder: Path) -> None:
    """``folder/README.md`` from ``before.json`` and ``after.json`` (issue 25) and,
    where they exist, ``before_issue42.json`` and ``after_issue42.json``."""
    runs = {k: json.loads((folder / f"{k}.json").read_text())
            for k in ("before", "after")}  # fmt: skip
    before, after = runs["before"], runs["after"]
    lines = [
        README_HEAD.format(
            before=before["commit"],
            before_lib=before["library"],
            after=after["commit"],
        ).rstrip("\n")
    ]
    table = _tables(before, after, CLASSES, TESTS)
    cut = table.index("")  # the class table, then every case under its heading
    lines += table[2:cut] + ["", "## Every case", ""] + table[cut + 1 :]
    lines.append(README_NOTES.format(budget=MEMORY_BUDGET / 1e9))
    if (folder / "after_issue42.json").exists():
        new = {k: json.loads((folder / f"{k}_issue42.json").read_text())
               for k in ("before", "after")}  # fmt: skip
        lines.append(README_42.format(before=new["before"]["commit"],
                                      after=new["after"]["commit"]))  # fmt: skip
        table = _tables(new["before"], new["after"], CLASSES_42, TESTS_42)
        cut = table.index("")
        lines += table[:cut] + ["", "### Every case of issue 42", ""]
        lines += table[cut + 1 :] + [README_42_NOTES]
    (folder / "README.md").write_text("\n".join(lines))
    print(f"wrote {folder / 'README.md'}")


README_42 = """
## Issue 42: functions, options, files, warnings, globals, bounds, screening, security

The same script with `issue=42` (`before_issue42.json`, `after_issue42.json`):

```bash
git worktree add /tmp/before 8980d6e
(cd /tmp/before && JAX_PLATFORMS=cpu PYTHONPATH=/tmp/before \\
  /work/main/.venv/bin/python /work/main/experiments/hostile_probe.py \\
  out=/work/main/results/hostile label=before issue=42)
JAX_PLATFORMS=cpu .venv/bin/python experiments/hostile_probe.py \\
  out=results/hostile label=after issue=42
.venv/bin/python experiments/hostile_probe.py report=results/hostile
```

Before: {before}; after: {after}. The outcomes follow the rules above; a case that
loads a run or runs a command does so in a child process where the harm (a marker
file written by code that should not have run, a planted program used) is read
from the disk, so code that ran and then failed is counted as silent wrong.
"""

README_42_NOTES = """
Reading the numbers:

- Security: a clear error must come from jaxcal (its own frame), be a
  `ValueError` or jaxcal's own class and name the consent (`trust_code`), the
  module or the folder; "correct" means nothing outside the installed package ran
  and the right model or program was used.
- Files, read-only folder: the probe runs as root here, who may write into a
  folder of mode 0555, so the write succeeding is the correct result.
- Screening: the stuck sensor is correct when no row of the unit's good outputs is
  skipped as an outlier, flagged when the stuck output is named; the three-row
  noise is right only with a word asking for `noise=`.
"""


def main(argv: list[str]) -> int:
    args = dict(a.split("=", 1) for a in argv)
    unknown = set(args) - {"out", "label", "only", "report", "child", "issue"}
    if unknown:
        print(f"unknown arguments {sorted(unknown)}; use out=DIR label=before|after "
              "[only=CASE] or report=DIR", file=sys.stderr)  # fmt: skip
        return 2
    if args.get("child") == "memory":
        memory_child()
    elif "report" in args:
        write_report(Path(args["report"]))
    else:
        label = args.get("label", "after")
        if label not in ("before", "after"):
            print(f"label must be before or after, got {label!r}", file=sys.stderr)
            return 2
        issue = args.get("issue", "25")
        if issue not in ("25", "42"):
            print(f"issue must be 25 or 42, got {issue!r}", file=sys.stderr)
            return 2
        probe(Path(args.get("out", "results/hostile")), label, args.get("only"),
              issue)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
