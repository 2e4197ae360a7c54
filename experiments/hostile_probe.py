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


def probe(out: Path, label: str, only: str | None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix=f"hostile_{label}_"))
    ctx = Context(root)
    records = []
    try:
        for case in all_cases():
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
        for k in CLASSES
    }  # fmt: skip
    report = {
        "label": label,
        "library": LIBRARY,
        "commit": _commit(),
        "command": " ".join([os.path.relpath(__file__), *sys.argv[1:]]),
        "counts": counts,
        "cases": records,
    }
    (out / f"{label}.json").write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {out / f'{label}.json'}")


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


def write_report(folder: Path) -> None:
    """``folder/README.md`` from ``before.json`` and ``after.json``."""
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
    for klass in CLASSES:
        n = sum(r["class"] == klass for r in after["cases"])
        tests = "<br>".join(f"`{t}`" for t in TESTS[klass])
        lines.append(
            f"| {klass} | {n} | {_counts_cell(before['counts'][klass])} | "
            f"{_counts_cell(after['counts'][klass])} | {tests} |"
        )
    total = {
        label: {o: sum(r["outcome"] == o for r in run["cases"]) for o in OUTCOMES}
        for label, run in runs.items()
    }
    lines.append(
        f"| **all** | {len(after['cases'])} | {_counts_cell(total['before'])} | "
        f"{_counts_cell(total['after'])} | |"
    )
    lines += [
        "",
        "## Every case",
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
    lines.append(README_NOTES.format(budget=MEMORY_BUDGET / 1e9))
    (folder / "README.md").write_text("\n".join(lines))
    print(f"wrote {folder / 'README.md'}")


def main(argv: list[str]) -> int:
    args = dict(a.split("=", 1) for a in argv)
    unknown = set(args) - {"out", "label", "only", "report", "child"}
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
        probe(Path(args.get("out", "results/hostile")), label, args.get("only"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
