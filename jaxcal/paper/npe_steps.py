"""The NPE peer's steps of the paper experiment, and its table in the report.

Three resumable steps of ``experiments/paper.py`` on Dataset #1, each a JSON-ready
dict like the other methods' steps:

* :func:`fit_step` (``fit-ds1-NPE``): sbi's NPE on pairs drawn from E2E-sim's simulated
  flights (:meth:`~jaxcal.paper.suite.Suite.simulated`, the same seed, so the same
  simulations), the posterior stored under the suite's model folder;
* :func:`evaluate_step` (``eval-ds1-NPE-clean``): the posterior over the scored test
  units, whole trajectories — theta RMSE of the posterior mean (pooled, per parameter,
  per unit, as :func:`jaxcal.paper.compare.evaluate_method` scores), 90 % coverage,
  batched deploy seconds per sample;
* :func:`latency_step` (``latency-ds1-NPE``): single-stream seconds per sample.

Without ``sbi``/``torch`` a step returns ``{"skipped": <install hint>}`` rather than
raising, and :func:`npe_table` shows that hint in the report.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np

from jaxcal.paper import npe
from jaxcal.training.scoring.trajectories import theta_rmse

STEPS = ("fit-ds1-NPE", "eval-ds1-NPE-clean", "latency-ds1-NPE")


def _posterior_path(suite) -> Path:
    return Path(suite.model_dir) / "npe-posterior.pt"


def _skipped(err: npe.NPEUnavailable) -> dict:
    return {"method": "NPE", "skipped": str(err)}


def _test_inputs(suite):
    units = suite.test_units()
    mask = units.mask
    return (
        units,
        mask,
        npe.npe_features(units.w[mask], units.x[mask], suite.problem.norm),
    )


def fit_step(suite, cfg: npe.NPEConfig, *, seed: int) -> dict:
    """Fit NPE on E2E-sim's simulations and store the posterior.

    Returns:
        ``{"method", "fit_seconds", "simulate_seconds", "epochs_run",
        "best_val_loss", "num_samples", "num_simulated", "posterior", "npe"}``, or
        ``{"skipped": ...}`` without sbi.
    """
    try:
        npe.require_sbi()
    except npe.NPEUnavailable as err:
        return _skipped(err)
    units, solved, sim_seconds = suite.simulated(seed)
    key_pairs = jax.random.fold_in(jax.random.key(seed), 1)
    theta, feats = npe.training_pairs(
        key_pairs, units, suite.problem.norm, cfg.max_samples
    )
    posterior, info = npe.fit_npe(
        theta, feats, suite.problem.theta_low, suite.problem.theta_high, cfg,
        seed=seed,
    )  # fmt: skip
    path = npe.save_posterior(_posterior_path(suite), posterior, cfg)
    return {
        "method": "NPE",
        **info,
        "train_seconds": info["fit_seconds"],  # the key the report's set-up reads
        "simulate_seconds": sim_seconds,
        "simulated_share_solved": solved,
        "num_simulated": int(units.mask.sum()),
        "units": units.unit_ids.tolist(),
        "posterior": str(path),
        "npe": dataclasses.asdict(cfg),
    }


def evaluate_step(suite, cfg: npe.NPEConfig, *, seed: int) -> dict:
    """Score the stored posterior on the suite's test units (whole trajectories).

    Returns:
        ``theta_rmse`` (+ per parameter, per unit), ``coverage90`` (+ Gaussian and per
        parameter, interval widths), ``deploy_s_per_sample_batched``,
        ``batched_samples_per_s``, ``num_samples``, ``units``; or ``{"skipped"}``.
    """
    try:
        posterior = npe.load_posterior(_posterior_path(suite))
    except npe.NPEUnavailable as err:
        return _skipped(err)
    units, mask, feats = _test_inputs(suite)
    summary = npe.posterior_summary(posterior, feats, cfg, seed=seed)
    names = list(suite.problem.theta_names)
    theta_hat = np.full(units.theta.shape, np.nan)
    theta_hat[mask] = summary["mean"]
    pooled, per_param = theta_rmse(theta_hat, units.theta, mask)
    per_unit = np.sqrt(
        np.nanmean((theta_hat - units.theta) ** 2, axis=(1, 2))
    )  # NaN (padding) rows drop out
    n = int(mask.sum())
    return {
        "dataset": "ds1",
        "variant": "clean",
        "method": "NPE",
        "theta_rmse": pooled,
        "theta_rmse_per_param": dict(zip(names, per_param.tolist(), strict=True)),
        "theta_rmse_per_unit": dict(
            zip(map(str, units.unit_ids.tolist()), per_unit.tolist(), strict=True)
        ),
        **npe.interval_scores(summary, units.theta[mask], names),
        "theta_finite": bool(np.isfinite(summary["mean"]).all()),
        "num_samples": n,
        "num_scored": n,
        "units": units.unit_ids.tolist(),
        "deploy_seconds": summary["seconds"],
        "deploy_s_per_sample_batched": summary["seconds"] / n,
        "batched_samples_per_s": n / summary["seconds"],
        "seed": seed,
        "info": {"posterior": str(_posterior_path(suite)), **dataclasses.asdict(cfg)},
    }


def latency_step(suite, cfg: npe.NPEConfig, *, repeats: int, seed: int) -> dict:
    """Single-stream seconds per sample of the stored posterior (first test unit)."""
    try:
        posterior = npe.load_posterior(_posterior_path(suite))
    except npe.NPEUnavailable as err:
        return _skipped(err)
    units, mask, feats = _test_inputs(suite)
    first = feats[: int(mask[0].sum())]
    return npe.single_stream_latency(posterior, first, cfg, repeats=repeats, seed=seed)


def _sci(value) -> str:
    return "–" if value is None else f"{value:.2e}"


def npe_table(steps: dict, *, available: bool | None = None) -> list[str]:
    """Markdown lines: "Amortised inference peer (NPE, sbi)" beside UKF and E2E-sim.

    Args:
        steps: step name -> stored result of ``experiments/paper.py``.
        available: whether sbi is installed (None: look); only used to explain a
            table without NPE results.
    """
    fit, ev, lat = (steps.get(name) or {} for name in STEPS)
    skipped = next((s["skipped"] for s in (fit, ev, lat) if "skipped" in s), None)
    if not ev or skipped:
        if available is None:
            available = npe.is_available()
        reason = skipped or ("not run" if available else npe.MISSING_HINT)
        return [f"NPE not scored: {reason}."]
    rows = []
    for method, label in (("UKF", "UKF on F"), ("E2E-sim", "E2E-sim")):
        e = steps.get(f"eval-ds1-{method}-clean")
        if e is None:
            continue
        single = (steps.get(f"latency-ds1-{method}") or {}).get("median_s")
        train = (steps.get(f"fit-ds1-{method}") or {}).get("train_seconds")
        rows.append(
            [label, _sci(e["theta_rmse"]), "–", "–", _sci(single),
             _sci(1.0 / e["batched_samples_per_s"]),
             "0" if method == "UKF" else f"{train:.0f}" if train else "–"]
        )  # fmt: skip
    rows.append(
        [f"NPE ({ev['info']['density_estimator']}, sbi)", _sci(ev["theta_rmse"]),
         f"{ev['coverage90']:.3f}", f"{ev['coverage90_gauss']:.3f}",
         _sci(lat.get("median_s")), _sci(ev["deploy_s_per_sample_batched"]),
         f"{fit['fit_seconds']:.0f}" if fit else "–"]
    )  # fmt: skip
    header = ["method", "theta RMSE", "coverage90 (5-95 % quantiles)",
              "coverage90 (mean ± 1.645 std)", "deploy s/sample single",
              "deploy s/sample batched", "fit s"]  # fmt: skip
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    num, total = fit.get("num_samples", 0), fit.get("num_simulated", 0)
    used = "all of" if num == total else f"{num:,} pairs drawn from"
    return lines + [
        "",
        f"NPE: sbi's NPE_C ({ev['info']['density_estimator']}) fitted on {used} "
        f"E2E-sim's {fit.get('num_simulated', 0):,} simulated samples "
        f"({fit.get('epochs_run')} "
        f"epochs; the simulation, {fit.get('simulate_seconds', 0):.0f} s, is shared "
        "with E2E-sim and not in fit s), per-sample inputs [w, x] standardised, "
        f"{ev['info']['num_posterior_samples']} posterior draws per test sample; its "
        f"estimate is their mean, scored on {ev['num_samples']:,} test samples; torch "
        f"on {ev['info']['num_threads']} CPU thread(s). E2E-sim's fit s includes "
        "its simulation.",
    ]
