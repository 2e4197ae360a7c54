"""The paper reproduction's published numbers, table helpers and first two tables.

Each ``*_table`` function (here and in :mod:`jaxcal.paper.study_tables`) turns the
step results of ``experiments/paper.py`` (step name -> JSON, wrapped in
:class:`Results`) into Markdown lines: inference RMSE, deployment and training time,
model bias / noise, sensor noise, tracking, LAC vs CLAC and scalability
(design/calibration.md, "The paper's results", items 1-6). Every table puts the
paper's value (:data:`PAPER`, copied from its tables) next to ours and adds the
ratios that compare across set-ups — the data, engine models and units differ from
the paper's, so absolute values do not. Missing results show as "–"; nothing here
computes a result.
"""

from __future__ import annotations

import math

from jaxcal.calibrators.methods import REGISTRY

# Published values (Tian et al., Tables "inference", "time", "robust_track",
# "sensor_noise", "tracking" and the ablation paragraph). None: not run ("–");
# "failed": the paper's "#" (UKF did not give a stable inference).
PAPER = {
    "inference": {
        "ds1": {"UKF": 3.42e-4, "E2E": 1.36e-3, "CLAC": 3.30e-4},
        "ds2": {"UKF": 3.51e-3, "E2E": None, "CLAC": 2.50e-3},
    },
    "deploy_s": {"UKF": 6.0, "E2E": 4.2e-4, "CLAC": 4.0e-4},
    "train_s": {"UKF": 0.0, "E2E": 200.0, "CLAC": 6200.0},
    "bias": {"UKF": 2.04e-3, "CLAC": 3.30e-4},
    "noise": {"UKF": "failed", "CLAC": 4.22e-4},
    "snr70": {"UKF": 3.72e-4, "CLAC": 7.18e-4},
    "tracking": {
        "ds1": {"UKF": 0.62, "CLAC": 0.98},
        "ds2": {"UKF": 1.78, "CLAC": 5.54},
    },
    "ablation": {"LAC": 1.3e-3, "CLAC": 3.3e-4},
}
# the registered methods on the model beside the paper's UKF (least squares, ...)
ON_MODEL = tuple(m.label for m in REGISTRY.values() if m.on_model and m.label != "UKF")
EXTRA = ("LAC", "SAC", "CLAC-F", "CLAC-inc", "CLAC-gate", *ON_MODEL, "E2E-sim")
# trained through python -m jaxcal.train
POLICIES = ("CLAC", "LAC", "SAC", "CLAC-F", "CLAC-inc")
# composed from trained policies (jaxcal.paper.gate_steps): CLAC-inc gated by CLAC
COMPOSED = ("CLAC-gate",)
NAMES = {
    "UKF": "UKF on F",
    "E2E": "E2E (labelled units)",
    "CLAC": "CLAC",
    "LAC": "LAC",
    "SAC": "SAC",
    "LS": "least squares on F",
    "E2E-sim": "E2E-sim (simulated labels)",
    "CLAC-F": "CLAC on F (dynamics=physics)",
    "CLAC-inc": "CLAC-inc (increments through F)",
    "CLAC-gate": "CLAC-gate (CLAC-inc, CLAC where F misfits)",
}
NAMES.update({m: f"{m} on F" for m in ON_MODEL if m not in NAMES})


def fmt(value, digits: int = 3) -> str:
    """A number for a table: ``3.42e-04``; missing -> ``–``; strings kept."""
    if value is None:
        return "–"
    if isinstance(value, str):
        return value
    if not math.isfinite(value):
        return "diverged (non-finite)"
    return f"{value:.{digits - 1}e}"


def ratio(a, b) -> float | None:
    """``a / b`` when both are positive numbers, else None."""
    ok = all(isinstance(v, (int, float)) and math.isfinite(v) for v in (a, b))
    return a / b if ok and b > 0 else None


class Results:
    """Typed access to the step results (step name -> stored JSON)."""

    def __init__(self, steps: dict):
        self.steps = steps

    def eval(self, ds: str, method: str, variant: str = "clean") -> dict | None:
        """The evaluation step of ``method`` on data set ``ds``, or None."""
        return self.steps.get(f"eval-{ds}-{method}-{variant}")

    def theta(self, ds: str, method: str, variant: str = "clean"):
        """Its pooled theta RMSE, or None."""
        ev = self.eval(ds, method, variant)
        return None if ev is None else ev["theta_rmse"]

    def coverage(self, ds: str, method: str, variant: str = "clean"):
        """Its 90 % interval coverage, or None (no run, or no std)."""
        ev = self.eval(ds, method, variant)
        return None if ev is None else ev.get("coverage90")

    def tracking(self, ds: str, method: str, variant: str = "clean"):
        """Its normalised tracking RMSE, or None."""
        ev = self.eval(ds, method, variant)
        return None if ev is None else ev.get("tracking_rmse_norm")

    def train(self, ds: str, agent: str) -> dict | None:
        """The training step of ``agent`` on ``ds`` (its final.json), or None."""
        return self.steps.get(f"train-{ds}-{agent.lower()}")


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table (header, separator, rows)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(r) + " |" for r in rows]


def ratio_line(label: str, ours, paper) -> str:
    """A bullet comparing our ratio with the paper's."""
    return (
        f"* {label}: ours **{fmt(ours) if ours is None else f'{ours:.2f}'}**, paper "
        f"{'–' if paper is None else f'{paper:.2f}'}"
    )


def share(value) -> str:
    """A share as a percentage (``88.1 %``); missing -> "–"."""
    return "–" if value is None else f"{100 * value:.1f} %"


def inference_table(r: Results) -> list[str]:
    """Paper Table "inference": theta RMSE per method and data set (with the 90 %
    coverage of the methods that report a std), per parameter on Dataset #2, E2E per
    unit, and the check against the training job's score."""
    rows = []
    for method in ("UKF", "E2E", "CLAC", *EXTRA):
        paper = [PAPER["inference"][ds].get(method) for ds in ("ds1", "ds2")]
        rows.append(
            [NAMES[method], fmt(r.theta("ds1", method)), fmt(paper[0]),
             fmt(r.theta("ds2", method)), fmt(paper[1]),
             share(r.coverage("ds1", method)), share(r.coverage("ds2", method))]
        )  # fmt: skip
    out = table(
        ["method", "Dataset #1 ours", "paper", "Dataset #2 ours", "paper",
         "90 % coverage #1", "90 % coverage #2"],
        rows,
    ) + ["", "90 % coverage: share of scored samples whose true theta lies within "
         "+-1.6449 times the method's reported std (methods without a std: –); an "
         "honest band covers about 90 %.", ""]  # fmt: skip
    out += clac_over_ukf_lines(r.theta, PAPER["inference"], "")
    out.append(
        ratio_line(
            "Dataset #1 E2E / CLAC",
            ratio(r.theta("ds1", "E2E"), r.theta("ds1", "CLAC")),
            ratio(PAPER["inference"]["ds1"]["E2E"], PAPER["inference"]["ds1"]["CLAC"]),
        )
    )
    ev = r.eval("ds2", "CLAC")
    if ev is not None:
        names = list(ev["theta_rmse_per_param"])
        out += ["", "Dataset #2 per parameter (theta RMSE):", ""]
        rows = []
        for method in ("UKF", *ON_MODEL, "E2E", "E2E-sim", "CLAC"):
            e = r.eval("ds2", method)
            if e is not None:
                rows.append(
                    [NAMES[method]] + [fmt(e["theta_rmse_per_param"][n]) for n in names]
                )
        out += table(["method", *names], rows)
    e2e = r.eval("ds1", "E2E")
    if e2e is not None:
        per_unit = ", ".join(
            f"unit {u}: {fmt(v)}" for u, v in e2e["theta_rmse_per_unit"].items()
        )
        out += ["", f"E2E per test unit of Dataset #1: {per_unit}."]
    clac = r.eval("ds1", "CLAC")
    if clac is not None and clac.get("training_job_theta_rmse") is not None:
        out += [
            "",
            f"Check: our CLAC run on Dataset #1 gives {fmt(clac['theta_rmse'], 4)}; "
            f"the training job scored {fmt(clac['training_job_theta_rmse'], 4)} on its "
            "test units (equal when the whole trajectories are scored).",
        ]
    return out


def _latency_form_lines(r: Results) -> list[str]:
    """How the single-stream latencies were taken: the deployed form (no noise key)
    and, for a policy on F, the model's solve warm-started from the previous sample."""
    names = ("UKF", "E2E", "CLAC", *EXTRA)
    steps = {m: r.steps.get(f"latency-ds1-{m}") or {} for m in names}
    warm = [NAMES[m] for m in names if steps[m].get("stream_form")]
    keyed = [
        NAMES[m]
        for m in names
        if steps[m] and not steps[m].get("deploy_form") and m not in ("E2E", "E2E-sim")
    ]
    out = []
    if any(s.get("deploy_form") for s in steps.values()):
        out += [
            "",
            "Latency: each method as deployed, one sample per call on the clean "
            "model: the calibrator alone, without the noise key the robustness runs "
            "carry in its state (a PRNG key in a jitted call's arguments takes JAX's "
            "slower dispatch path; `experiments/cpubench/engine_latency.py` times "
            "both forms; the E2E network never had one)."
            + (
                f" Measured before that change, with the key: {', '.join(keyed)}."
                if keyed
                else ""
            ),
        ]
    if warm:
        out += [
            "",
            f"Single-stream forms ({', '.join(warm)}): a policy on F carries the "
            "engine's Newton solution from sample to sample and closes the next "
            "balance with Broyden updates (the cold solve when they do not), as "
            "`StreamingCalibrator.step` runs; scores and batched runs keep the cold "
            "solve. Its outputs agree with the cold solve's to the solver's tolerance "
            "(`tests/paper/test_stream_form.py`; "
            "`experiments/cpubench/engine_latency.py` measures the theta difference). "
            "A policy latency step without `stream_form` was measured before the warm "
            "start (CLAC on F's).",
        ]
    return out


def clac_over_ukf_lines(score, paper: dict, what: str) -> list[str]:
    """CLAC / UKF ratio of ``score(ds, method)`` on both data sets, beside the
    paper's (``paper[ds][method]``); ``what`` names the score in the label."""
    return [
        ratio_line(
            f"{label} {what}CLAC / UKF",
            ratio(score(ds, "CLAC"), score(ds, "UKF")),
            ratio(paper[ds]["CLAC"], paper[ds]["UKF"]),
        )
        for ds, label in (("ds1", "Dataset #1"), ("ds2", "Dataset #2"))
    ]


def timing_table(r: Results) -> list[str]:
    """Paper Table "time": seconds per sample (single stream), batched throughput and
    training time on Dataset #1."""
    rows = []
    for method in ("UKF", "E2E", "CLAC", *EXTRA):
        lat = r.steps.get(f"latency-ds1-{method}")
        ev = r.eval("ds1", method)
        train = r.train("ds1", method) if method in POLICIES else None
        fit = r.steps.get(f"fit-ds1-{method}")
        if train is not None:
            # Compute seconds of both fits, summed over sessions (a resumed run's
            # wall time covers only its last session unless the run recorded a total).
            fit_d = (train.get("surrogate") or {}).get("fit_seconds")
            policy = train["train_seconds"]
            train_s = (
                f"{policy:.0f} (policy on F)"
                if fit_d is None
                else f"{fit_d + policy:.0f} (D {fit_d:.0f} + policy {policy:.0f})"
            )
        elif method in COMPOSED:
            train_s = "CLAC's + CLAC-inc's" if ev is not None else "–"
        elif fit is not None:
            train_s = f"{fit['train_seconds']:.0f}"
        else:  # UKF and least squares learn nothing
            train_s = "0" if ev is not None else "–"
        paper_dep = PAPER["deploy_s"].get(method)
        paper_train = PAPER["train_s"].get(method)
        rows.append(
            [NAMES[method],
             "–" if lat is None else fmt(lat["median_s"]),
             fmt(paper_dep),
             "–" if ev is None else f"{ev['batched_samples_per_s']:,.0f}",
             train_s,
             "–" if paper_train is None else f"{paper_train:.0f}"]
        )  # fmt: skip
    out = table(
        ["method", "single-stream s/sample (median)", "paper s/sample",
         "batched samples/s (test units vmapped)", "training s", "paper training s"],
        rows,
    ) + [""]  # fmt: skip
    shown = ("CLAC", "CLAC-inc", "CLAC-gate")
    lat = {m: r.steps.get(f"latency-ds1-{m}") for m in ("UKF", *shown)}
    for policy in shown:
        ours = None
        if lat["UKF"] is not None and lat[policy] is not None:
            ours = ratio(lat["UKF"]["median_s"], lat[policy]["median_s"])
        if policy == "CLAC" or ours is not None:
            out.append(
                ratio_line(
                    f"UKF / {policy} deployment time", ours,
                    ratio(PAPER["deploy_s"]["UKF"], PAPER["deploy_s"]["CLAC"]),
                )
            )  # fmt: skip
    clac = r.train("ds1", "CLAC")
    paper_clac = PAPER["train_s"]["CLAC"]
    if clac is not None:
        ours_s = (clac.get("surrogate") or {}).get("fit_seconds", 0.0) + clac[
            "train_seconds"
        ]
        out.append(
            f"* CLAC training time, paper {paper_clac:.0f} s / ours {ours_s:.0f} s: "
            f"**{paper_clac / ours_s:.2f}** (other data, other CPU: an indication)"
        )
    out += [
        "",
        "Training s of the policies: seconds spent fitting the surrogate D plus "
        "training the policy (the jitted updates and environment steps, summed over "
        "the run's sessions; compilation and the evaluations between chunks are "
        "outside it, see the wall times under Set-up). E2E: its fit.",
    ]
    return out + _latency_form_lines(r)


def num(value) -> str:
    """A plain number for a table (four decimals); missing -> "–"."""
    if value is None:
        return "–"
    return f"{value:.4f}" if math.isfinite(value) else "diverged"
