"""Stage 1 of a training run: fit the surrogate D on the training units, or restore it.

D (paper §3.1 and appendix "Simulator Network"; :mod:`jaxcal.surrogate`) learns
x_{t+1} = D(w_{t+1}, x_t, theta_{t+1}) from the consecutive samples of the training
units, whose x are the physics outputs F(w, theta) of the generated file (for a NASA
file: the recorded sensors). The report gives, per sensor, the one-step error (D fed the
measured x_t) and the free-running error (D fed back its own output from x-hat_0 = x_0,
as in the environment) on the validation and test units, in sensor units and divided by
the sensor's training std. The fitted D is saved as an Orbax checkpoint in the run
folder; a resumed run restores it instead of refitting, so its policy stage sees the
very same dynamics.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from jaxcal.data.padded import Padded
from jaxcal.runs.checkpoint import Checkpointer
from jaxcal.runs.folder import SURROGATE_DIR, SURROGATE_FILE, read_json, write_json
from jaxcal.surrogate.fit import fit_surrogate, make_transitions, surrogate_errors
from jaxcal.surrogate.model import (
    SurrogateConfig,
    SurrogateParams,
    init_surrogate_params,
)
from jaxcal.training.data.calibration import CalibrationData
from jaxcal.training.scoring.trajectories import describe_units
from jaxcal.typedefs import PRNGKey


def _split_errors(params: SurrogateParams, units: Padded, sensors) -> dict:
    errors = surrogate_errors(params, units.w, units.x, units.theta, units.mask)
    out = {"num_pairs": errors["num_pairs"]}
    for kind in ("one_step", "free_run"):
        out[f"{kind}_rmse_norm_mean"] = float(errors[f"{kind}_rmse_norm_mean"])
        for suffix in ("rmse", "rmse_norm"):
            values = np.asarray(errors[f"{kind}_{suffix}"]).tolist()
            out[f"{kind}_{suffix}"] = dict(zip(sensors, values, strict=True))
    return out


def fit_or_restore_surrogate(
    key: PRNGKey,
    data: CalibrationData,
    cfg: SurrogateConfig,
    run_dir: str | Path,
    *,
    progress: bool = False,
    log: Callable[[str], None] = print,
) -> tuple[SurrogateParams, dict]:
    """The run's surrogate D and its report (fitting it on first use).

    Args:
        key: PRNG key of the fit (initialisation, validation split, minibatches).
        data: the run's data; D is fitted on ``data.train`` only.
        cfg: architecture and optimisation settings.
        run_dir: run folder (``surrogate/`` and ``surrogate.json`` live there).
        progress: show a progress bar over epochs.
        log: where one-line summaries go.

    Returns:
        ``(params, report)``; the report holds the fit summary (``epochs_run``,
        ``best_epoch``, ``final_val_loss``, ``fit_seconds``) and the per-sensor errors
        on ``val`` (when present) and ``test``.
    """
    run_dir = Path(run_dir)
    ckpt_dir = run_dir / SURROGATE_DIR
    dims = (
        data.train.w.shape[-1],
        len(data.problem.output_names),
        len(data.problem.theta_names),
    )
    with Checkpointer(ckpt_dir, max_to_keep=1) as ckpt:
        if ckpt.latest_step() is not None and (run_dir / SURROGATE_FILE).is_file():
            target = jax.eval_shape(
                lambda k: init_surrogate_params(k, *dims, cfg), jax.random.key(0)
            )
            params = ckpt.restore(None, target)
            report = read_json(run_dir / SURROGATE_FILE)
            log(f"surrogate D restored from {ckpt_dir}")
            log(format_surrogate_report(report))
            return params, report
        train = data.train
        transitions = make_transitions(train.w, train.x, train.theta, train.mask)
        log(
            f"fitting surrogate D {cfg.hidden_sizes} on {len(transitions.x):,} "
            f"transitions of units {describe_units(train.unit_ids)}"
        )
        start = time.perf_counter()
        params, history = fit_surrogate(key, transitions, cfg, progress=progress)
        seconds = time.perf_counter() - start
        report = {
            "hidden_sizes": list(cfg.hidden_sizes),
            "num_transitions": len(transitions.x),
            "epochs_run": history["epochs_run"],
            "best_epoch": history["best_epoch"],
            "final_train_loss": float(history["train_loss"][-1]),
            "final_val_loss": (
                float(history["val_loss"][history["best_epoch"]])
                if len(history["val_loss"])
                else None
            ),
            "fit_seconds": seconds,
        }
        for split in ("val", "test"):
            units = getattr(data, split)
            if units is not None and units.theta is not None:
                report[split] = _split_errors(params, units, data.problem.output_names)
        ckpt.save(0, params, wait=True)
    write_json(run_dir / SURROGATE_FILE, report)
    log(format_surrogate_report(report))
    return params, report


def format_surrogate_report(report: dict) -> str:
    """Per-sensor one-step / free-running errors of D as printable lines."""
    where = "val" if "val" in report else "test"
    if where not in report:  # held-out units without true parameters: no D error
        seconds = report["fit_seconds"]
        return f"surrogate D: {report['epochs_run']} epochs in {seconds:.0f} s"
    errors = report[where]
    lines = [
        f"surrogate D: {report['epochs_run']} epochs in {report['fit_seconds']:.0f} s;"
        f" {where} units, RMSE / training std (mean over sensors: one-step "
        f"{errors['one_step_rmse_norm_mean']:.4f}, free-running "
        f"{errors['free_run_rmse_norm_mean']:.4f})"
    ]
    for kind in ("one_step", "free_run"):
        lines.append(
            f"  {kind.replace('_', '-'):9s} "
            + " ".join(f"{k} {v:.4f}" for k, v in errors[f"{kind}_rmse_norm"].items())
        )
    return "\n".join(lines)
