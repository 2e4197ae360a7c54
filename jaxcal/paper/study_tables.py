"""The paper's robustness, sensor-noise, tracking, ablation and scalability tables.

The second half of the reproduction's tables (:mod:`jaxcal.paper.tables` has the
published numbers, the helpers and the inference and timing tables): model bias /
noise, 70 dB sensor noise, tracking RMSE, LAC vs CLAC and d = 1, 2, 4, each beside the
paper's value and the ratios that compare across set-ups. Missing results show as "–";
nothing here computes a result.
"""

from __future__ import annotations

from jaxcal.paper.tables import (
    COMPOSED,
    EXTRA,
    NAMES,
    PAPER,
    POLICIES,
    Results,
    clac_over_ukf_lines,
    fmt,
    num,
    ratio,
    ratio_line,
    share,
    table,
)


def robustness_table(r: Results) -> list[str]:
    """Paper Table "robust_track": theta RMSE under model bias and model noise."""
    rows = []
    labels = {"clean": "none", "bias": "bias F x 1.02", "noise": "noise F + N(0, 0.1)"}
    for variant, label in labels.items():
        paper = (
            PAPER.get(variant, {}) if variant != "clean" else PAPER["inference"]["ds1"]
        )
        rows.append(
            [label, fmt(r.theta("ds1", "UKF", variant)), fmt(paper.get("UKF")),
             fmt(r.theta("ds1", "CLAC", variant)), fmt(paper.get("CLAC")),
             fmt(r.theta("ds1", "LAC", variant)), fmt(r.theta("ds1", "SAC", variant)),
             fmt(r.theta("ds1", "CLAC-F", variant)),
             fmt(r.theta("ds1", "CLAC-inc", variant)),
             fmt(r.theta("ds1", "CLAC-gate", variant))]
        )  # fmt: skip
    out = table(
        ["model perturbation", "UKF ours", "paper", "CLAC ours", "paper", "LAC ours",
         "SAC ours", "CLAC on F ours", "CLAC-inc ours", "CLAC-gate ours"],
        rows,
    ) + [""]  # fmt: skip
    for variant in ("bias", "noise"):
        paper = PAPER[variant]
        for policy in ("CLAC", "CLAC-inc", "CLAC-gate"):
            ours = ratio(
                r.theta("ds1", policy, variant), r.theta("ds1", "UKF", variant)
            )
            if policy == "CLAC" or ours is not None:
                out.append(
                    ratio_line(
                        f"{labels[variant]}: {policy} / UKF", ours,
                        ratio(paper["CLAC"], paper["UKF"]),
                    )
                )  # fmt: skip
    scored = ("UKF", *POLICIES, *COMPOSED)
    covered = [
        f"{'clean' if v == 'clean' else labels[v]}: "
        + ", ".join(f"{m} {share(c)}" for m in scored
                    if (c := r.coverage("ds1", m, v)) is not None)
        for v in labels
        if any(r.coverage("ds1", m, v) is not None for m in scored)
    ]  # fmt: skip
    if covered:
        out += ["", "90 % coverage of the methods with a std: " + "; ".join(covered)]
    return out


def sensor_noise_table(r: Results) -> list[str]:
    """Paper Table "sensor_noise": theta RMSE on the 70 dB copy of Dataset #1."""
    rows = []
    for method in ("UKF", *POLICIES, *COMPOSED, "E2E", "E2E-sim"):
        rows.append(
            [NAMES[method], fmt(r.theta("ds1", method)),
             fmt(r.theta("ds1", method, "snr70")), fmt(PAPER["snr70"].get(method))]
        )  # fmt: skip
    out = table(["method", "clean ours", "70 dB ours", "70 dB paper"], rows) + [""]
    out.append(
        ratio_line(
            "70 dB: CLAC / UKF",
            ratio(r.theta("ds1", "CLAC", "snr70"), r.theta("ds1", "UKF", "snr70")),
            ratio(PAPER["snr70"]["CLAC"], PAPER["snr70"]["UKF"]),
        )
    )
    return out


def tracking_table(r: Results) -> list[str]:
    """Paper Table "tracking": normalised tracking RMSE on both data sets."""
    rows = []
    for method in ("UKF", "CLAC", *EXTRA, "E2E"):
        rows.append(
            [NAMES[method], f"{num(r.tracking('ds1', method))}",
             num(PAPER["tracking"]["ds1"].get(method)),
             num(r.tracking("ds2", method)),
             num(PAPER["tracking"]["ds2"].get(method))]
        )  # fmt: skip
    out = table(
        ["method", "Dataset #1 ours", "paper", "Dataset #2 ours", "paper"], rows
    ) + [""]
    return out + clac_over_ukf_lines(r.tracking, PAPER["tracking"], "tracking ")


def ablation_table(r: Results) -> list[str]:
    """The ablation paragraph: LAC vs CLAC (and SAC) on Dataset #1."""
    lac, clac, sac = (r.theta("ds1", m) for m in ("LAC", "CLAC", "SAC"))
    out = table(
        ["", "LAC", "CLAC", "SAC", "LAC / CLAC"],
        [
            ["ours", fmt(lac), fmt(clac), fmt(sac), num(ratio(lac, clac))],
            ["paper", fmt(PAPER["ablation"]["LAC"]), fmt(PAPER["ablation"]["CLAC"]),
             "–",
             num(ratio(PAPER["ablation"]["LAC"], PAPER["ablation"]["CLAC"]))],
        ],
    )  # fmt: skip
    return out


def scalability_table(r: Results, variants: list[str]) -> list[str]:
    """Scalability: UKF and CLAC theta RMSE for d = 1, 2, 4 on Dataset #2."""
    rows = []
    for ds in variants:
        ukf, clac = r.eval(ds, "UKF"), r.eval(ds, "CLAC")
        ref = clac or ukf
        if ref is None:
            continue
        names = list(ref["theta_rmse_per_param"])
        rows.append(
            [str(len(names)), ", ".join(names), str(len(ref["units"])),
             f"{ref['num_samples']:,}", fmt(r.theta(ds, "UKF")),
             fmt(r.theta(ds, "CLAC")),
             num(ratio(r.theta(ds, "CLAC"), r.theta(ds, "UKF")))]
        )  # fmt: skip
    rows.sort(key=lambda row: int(row[0]))
    return table(
        ["d", "declared parameters", "test scenarios", "samples", "UKF theta RMSE",
         "CLAC theta RMSE", "CLAC / UKF"],
        rows,
    )  # fmt: skip
