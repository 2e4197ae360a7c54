"""The comparison of the paper's methods on one data set: loading, building, scoring.

A :class:`Suite` holds everything the evaluation steps of one data set share, loaded
once and kept: the splits as the reference policy run read them (same sensors,
parameters, validation units and stride, :func:`jaxcal.models.turbofan.training.
load_calibration_data`), their :class:`~jaxcal.problem.Problem`, the engine
and the built methods. Its step functions return JSON-ready dicts:

* :meth:`Suite.fit_e2e`: the E2E network on labelled units (the paper's), or on the
  simulated flights of :func:`~jaxcal.paper.simulate.simulated_units` (E2E-sim);
* :meth:`Suite.evaluate`: one method, one variant (clean, model bias / noise, or a
  noisy copy of the data file), whole test trajectories;
* :meth:`Suite.latency`: the single-stream deployment cost.

Methods are built on first use, so that a resumed experiment loads only what it runs.
Every method runs guarded (:mod:`jaxcal.calibrators.interface`): samples it flags (NaN,
outside the engine's envelope or a policy's training range) are skipped, left out of
its scores and counted per reason in them (``flagged``, ``num_flagged``).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax
import numpy as np

from jaxcal.calibrators.interface import SampleCheck
from jaxcal.calibrators.methods import REGISTRY
from jaxcal.calibrators.methods.e2e.network import E2EConfig, fit_e2e, init_e2e_params
from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig
from jaxcal.calibrators.methods.policy.loading import load_run, needs_x64
from jaxcal.calibrators.ukf import UKFConfig
from jaxcal.data.padded import Padded
from jaxcal.models.turbofan.physics.engine import ENVELOPES, load_engine
from jaxcal.models.turbofan.training import load_calibration_data
from jaxcal.paper.compare import (
    MethodRun,
    evaluate_method,
    limit_units,
    measure_latency,
)
from jaxcal.paper.gate_steps import gated_method
from jaxcal.paper.methods import (
    Method,
    e2e_method,
    model_method,
    paper_config,
    policy_method,
)
from jaxcal.paper.npe import NPEConfig
from jaxcal.paper.simulate import (
    evaluate_declared,
    gather_units,
    simulated_units,
    subset_units,
)
from jaxcal.paper.steps import load_params, save_params
from jaxcal.runs.folder import DATA_FILE, read_json


@dataclasses.dataclass(frozen=True)
class SuiteConfig:
    """How the methods of one data set are built and scored."""

    max_test_units: int | None = None  # a seeded subset of N test units (None: all)
    max_steps: int | None = None  # cut each test unit to N samples (None: whole)
    ukf: UKFConfig = UKFConfig()  # paper: q = r = 0.01
    least_squares: LeastSquaresConfig = LeastSquaresConfig(window=4, num_iters=2)
    e2e: E2EConfig = E2EConfig()  # paper appendix: 3 x 100 ReLU, Adam 1e-4
    # labelled units of E2E: ids, or () for every training unit (capped below)
    e2e_units: tuple[int, ...] = ()
    e2e_max_samples: int = 300_000  # labelled / simulated samples E2E fits on
    # samples per engine call of F (the generator's chunk size shares its program)
    chunk_size: int = 8192
    npe: NPEConfig = NPEConfig()  # the NPE peer (sbi), fitted on E2E-sim's samples


class Suite:
    """Data, problem, engine and methods of one data set (see the module docstring).

    Args:
        data_path: the clean data file.
        runs: policy name (``"CLAC"``, ``"LAC"``, ``"SAC"``) -> run folder; the
            ``"CLAC"`` run fixes how the data are read.
        cfg: :class:`SuiteConfig`.
        model_dir: where fitted E2E weights are stored.
    """

    def __init__(self, data_path: str, runs: dict, cfg: SuiteConfig, model_dir):
        if "CLAC" not in runs:
            raise ValueError("a suite needs the CLAC run (it fixes the data reading)")
        self.data_path, self.runs, self.cfg = data_path, dict(runs), cfg
        self.model_dir = Path(model_dir)
        ref = read_json(Path(runs["CLAC"]) / DATA_FILE)
        run_cfg = read_json(Path(runs["CLAC"]) / "config.json")
        self._read = dict(
            sensors=tuple(ref["sensors"]),
            theta=tuple(ref["theta_names"]),
            val_units=tuple(ref["units"]["val"]),
            stride=int(run_cfg["dataset"]["stride"]),
            theta_margin=float(run_cfg["env"]["theta_margin"]),
        )
        self.data = load_calibration_data(data_path, **self._read)
        self.problem = self.data.problem
        self._engine = None
        self._methods: dict[str, Method] = {}
        self._test: dict[str, Padded] = {}
        self._simulated: dict[int, tuple[Padded, float, float]] = {}

    @property
    def engine(self):
        """The data set's engine (loaded on first use, in float64)."""
        if self._engine is None:
            with jax.enable_x64(True):  # else its design constants load as float32
                self._engine = load_engine(self.problem.model.name)
        return self._engine

    def test_units(self, data_path: str | None = None) -> Padded:
        """The scored test units of ``data_path`` (default: the clean file)."""
        path = data_path or self.data_path
        if path not in self._test:
            data = self.data if path == self.data_path else None
            if data is None:
                data = load_calibration_data(path, **self._read)
            self._test[path] = limit_units(
                data.test,
                max_units=self.cfg.max_test_units,
                max_steps=self.cfg.max_steps,
            )
        return self._test[path]

    def model_output(self, w: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """F(w, theta) at ``[N]`` samples (NaN where F does not solve)."""
        with jax.enable_x64(True):
            x, ok = evaluate_declared(
                self.engine, self.problem, w, theta, chunk_size=self.cfg.chunk_size
            )
        return np.where(ok[:, None], x, np.nan)

    def model_gap(self, *, num_samples: int, seed: int) -> dict:
        """How far today's F is from the file: |F(w, theta) - x| / std on test rows.

        A file generated by an older engine, or with noise, is not reproduced exactly
        by F; model-based methods then see that gap as model error.

        Returns:
            ``{"num_samples", "mean_norm", "max_norm", "per_sensor_max_norm",
            "unsolved"}`` over a seeded sample of valid test rows.
        """
        units = self.data.test
        rows = np.flatnonzero(units.mask.reshape(-1))
        pick = np.asarray(
            jax.random.choice(
                jax.random.key(seed), rows.size, (min(num_samples, rows.size),), False
            )
        )
        flat = rows[np.sort(pick)]
        w = units.w.reshape(-1, units.w.shape[-1])[flat]
        x = units.x.reshape(-1, units.x.shape[-1])[flat]
        theta = units.theta.reshape(-1, units.theta.shape[-1])[flat]
        gap = np.abs(self.model_output(w, theta) - x) / self.problem.norm.x_std
        solved = np.isfinite(gap).all(axis=1)
        gap = gap[solved]
        return {
            "num_samples": int(flat.size),
            "mean_norm": float(gap.mean()),
            "max_norm": float(gap.max()),
            "per_sensor_max_norm": dict(
                zip(self.problem.output_names, gap.max(axis=0).tolist(), strict=True)
            ),
            "unsolved": int((~solved).sum()),
        }

    # ------------------------------------------------------------------ methods

    def method(self, name: str) -> Method:
        """The method ``name``: UKF, LS, E2E, E2E-sim, a policy run or CLAC-gate."""
        if name not in self._methods:
            self._methods[name] = self._build(name)
        return self._methods[name]

    def forget(self, name: str) -> None:
        """Drop the built method ``name`` (its stored fit changed)."""
        self._methods.pop(name, None)

    def _build(self, name: str) -> Method:
        on_model = {m.label: m for m in REGISTRY.values() if m.on_model}
        if name in on_model:  # a registered method on the model, on the suite's F
            cfg = self.cfg
            table_cfg = paper_config(on_model[name], cfg.ukf, cfg.least_squares)
            return model_method(self.engine, self.problem, table_cfg, name)
        if name in ("E2E", "E2E-sim"):
            target = init_e2e_params(
                jax.random.key(0),
                self.data.train.w.shape[-1],
                len(self.problem.output_names),
                len(self.problem.theta_names),
                self.cfg.e2e,
            )
            params = load_params(self._e2e_path(name), target)
            info = {
                "weights": str(self._e2e_path(name)),
                **dataclasses.asdict(self.cfg.e2e),
            }
            # the engine's envelope, without loading the engine (G has no model)
            envelope = ENVELOPES.get(self.problem.model.name)
            check = None if envelope is None else SampleCheck(*envelope.w_box())
            return e2e_method(params, name, info, check)
        if name == "CLAC-gate":  # the two policies composed (gate_steps)
            return gated_method(self)
        if name in self.runs:
            # a policy on the engines' F loads its float64 params under x64 (the
            # process may not have trained it: a reused run)
            with jax.enable_x64(needs_x64(self.runs[name])):
                return policy_method(load_run(self.runs[name]), name)
        raise ValueError(f"unknown method {name!r} (no run given for it?)")

    def _e2e_path(self, name: str) -> Path:
        return self.model_dir / f"{name.lower()}.msgpack"

    # ------------------------------------------------------------------ steps

    def simulated(self, seed: int) -> tuple[Padded, float, float]:
        """E2E-sim's training flights (:func:`simulated_units`), simulated once per
        seed and kept, so that E2E-sim and the NPE peer learn from the same samples.

        Returns:
            ``(units, converged_share, seconds)``; the key is the one
            :meth:`fit_e2e` has always used (the first half of ``key(seed)``).
        """
        if seed not in self._simulated:
            key_sim, _ = jax.random.split(jax.random.key(seed))
            tic = time.perf_counter()
            with jax.enable_x64(True):
                units, solved = simulated_units(
                    key_sim, self.engine, self.problem, self.data.train,
                    max_samples=self.cfg.e2e_max_samples,
                    chunk_size=self.cfg.chunk_size,
                )  # fmt: skip
            self._simulated[seed] = (units, solved, time.perf_counter() - tic)
        return self._simulated[seed]

    def fit_e2e(self, name: str, *, seed: int) -> dict:
        """Fit E2E (labelled units) or E2E-sim (simulated labels); store the weights.

        Returns:
            ``{"train_seconds", "units", "num_samples", "epochs_run", "best_epoch",
            "best_val_loss", ...}``; training time includes simulating the labels.
        """
        key_sim, key_fit = jax.random.split(jax.random.key(seed))
        tic = time.perf_counter()
        extra = {}
        if name == "E2E-sim":
            units, solved, _ = self.simulated(seed)
            extra["simulated_share_solved"] = solved
        elif self.cfg.e2e_units:
            splits = [self.data.train, self.data.val, self.data.test]
            units = gather_units(splits, self.cfg.e2e_units)
        else:
            units = subset_units(key_sim, self.data.train, self.cfg.e2e_max_samples)
        params, history = fit_e2e(
            key_fit, units.w, units.x, units.theta, units.mask, self.cfg.e2e,
            progress=True,
        )  # fmt: skip
        seconds = time.perf_counter() - tic
        save_params(self._e2e_path(name), params)
        self._methods.pop(name, None)
        val = np.asarray(history["val_loss"])
        return {
            "method": name,
            "train_seconds": seconds,
            "units": units.unit_ids.tolist(),
            "num_samples": int(units.mask.sum()),
            "epochs_run": int(history["epochs_run"]),
            "best_epoch": int(history["best_epoch"]),
            "best_val_loss": float(val.min()) if val.size else None,
            "weights": str(self._e2e_path(name)),
            **extra,
        }

    def evaluate(
        self,
        name: str,
        *,
        seed: int,
        bias: float = 1.0,
        noise_sigma: float = 0.0,
        data_path: str | None = None,
    ) -> MethodRun:
        """Scores of method ``name`` on the test units (see :func:`evaluate_method`)."""
        method = self.method(name)
        units = self.test_units(data_path)
        with jax.enable_x64(method.dtype == np.float64):
            run = evaluate_method(
                method, units, self.problem, seed=seed, bias=bias,
                noise_sigma=noise_sigma, model_output=self.model_output,
            )  # fmt: skip
        run.scores["data"] = data_path or self.data_path
        clean = bias == 1.0 and noise_sigma == 0.0 and data_path is None
        if name in self.runs and clean:
            final = read_json(Path(self.runs[name]) / "final.json")["test"]
            run.scores["training_job_theta_rmse"] = final["theta_rmse"]
        return run

    def latency(self, name: str, *, repeats: int, seed: int) -> dict:
        """Single-stream seconds per sample of method ``name`` (clean model)."""
        method = self.method(name)
        with jax.enable_x64(method.dtype == np.float64):
            return measure_latency(
                method, self.test_units(), repeats=repeats, seed=seed
            )
