"""The battery example's figures (matplotlib, Agg): tracked R0 and Q over cycles,
and throughput against dynamax."""

from __future__ import annotations

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def tracking_figure(frame, tracks: dict, path: str) -> None:
    """Truth and every method's R0 and Q at the end of each cycle (the estimate a
    user reads after the cycle; the within-cycle traces of the sample-by-sample
    methods swing with the current and would hide the trend), one row per unit."""
    plt = _plt()
    units = sorted(frame.unit.unique())
    fig, axes = plt.subplots(len(units), 2, figsize=(11, 2.5 * len(units)), sharex=True)
    axes = np.atleast_2d(axes)
    for i, unit in enumerate(units):
        rows = np.flatnonzero((frame.unit == unit).to_numpy())
        part = frame.iloc[rows]
        last = part.groupby("cycle").tail(1).index  # frame labels of each cycle end
        pos = np.searchsorted(frame.index.to_numpy(), last.to_numpy())
        cycles = frame.loc[last, "cycle"].to_numpy() + 1
        for j, (col, label, scale) in enumerate(
            (("R0_true", "R0 [mOhm]", 1e3), ("Q_true", "Q [Ah]", 1.0))
        ):
            ax = axes[i, j]
            ax.plot(cycles, frame.loc[last, col] * scale, "k", lw=2.5, label="truth")
            for name, theta in tracks.items():
                ax.plot(cycles, theta[pos, j] * scale, ".-", lw=1.0, ms=4, label=name)
            ax.set_ylabel(f"unit {unit}: {label}")
            ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("cycles completed")
    axes[-1, 1].set_xlabel("cycles completed")
    axes[0, 1].legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def bench_figure(bench: dict, path: str) -> None:
    """Samples/s of jaxcal's and dynamax's UKF, single stream and fleet."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    labels = ["single stream", f"fleet of {bench['fleet_size']}"]
    for k, (name, color) in enumerate((("jaxcal", "C0"), ("dynamax", "C1"))):
        vals = [bench[s].get(name, 0.0) for s in ("single", "fleet")]
        bars = ax.bar(np.arange(2) + 0.38 * k, vals, 0.38, color=color, label=name)
        ax.bar_label(bars, fmt="%.3g", fontsize=8)
    labels = [
        lab + (f"\njaxcal / dynamax = {bench[s]['ratio']:.2f}" if "ratio" in bench[s] else "")
        for lab, s in zip(labels, ("single", "fleet"), strict=True)
    ]  # fmt: skip
    ax.set_xticks(np.arange(2) + 0.19, labels)
    ax.set_yscale("log")
    ax.set_ylabel("samples / s (after compilation)")
    ax.set_title(f"joint UKF on the battery ECM, {bench['steps']} steps per stream")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
