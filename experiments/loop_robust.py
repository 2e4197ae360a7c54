"""Detection curves of the closing-the-loop diagnosis on data it does not assume.

The older study (loop_study.py, results/loop/) draws its records from the settings the
diagnosis is built on. Here every record is drawn by :mod:`robust_scenario` (random
flight profiles, lives and sampling, wear shapes, noise level and AR(1) colour, number
of units and which of them carry the effect), the noise levels are *estimated* by the
diagnosis, and the effect size is a multiple of a stated detectability size.

**Detectability size** ``s1`` of an effect (per kind and target, :func:`detectability`):
on the nominal reference record (:func:`robust_scenario.reference_setting`), the
noise-free record with the effect at a probe size ``p`` is fitted with the declared
parameters only; the SSR left (in noise std, the reference noise) is the energy ``E``
of the part of the signature the declared parameters cannot absorb, and
``s1 = p sqrt(LR* / E)``, where ``LR*`` is what the diagnosis needs to call a single
candidate found (identify.py): ``LR* = max(bic_margin + df ln n, chi2_df^-1(1 -
alpha / num_tests))``, ``df`` = 1 (constant effects) or units x candidate knots (an
undeclared parameter). At 1x the expected likelihood-ratio statistic of the truth
equals the threshold on the reference record; the random records scatter around it.

Measured per kind and size multiple: **identification** (the diagnosis adds exactly the
true effect), **in confounded set**, **missed** (nothing added); on clean records the
**false-alarm** rate (any verdict but ``none``); per unit, from the diagnosis's
per-unit verdict (``carries``, Holm z-test, units.py), the **unit hit rate** (carrier
units flagged for the true effect, counted 0 when the truth is not added) and the
**unit false-flag rate** (non-carriers flagged, in records where the truth was added).

Resumable: one JSON line per record is appended to ``<out>/records.jsonl`` and done
records are skipped. Writes ``<out>/study.json``, ``<out>/detection.png`` and
``<out>/README.md``.

Usage::

    python experiments/loop_robust.py [seeds=4] [clean=20] [multiples=0.5,1,2,5,10]
        [kinds=parameter,t2_offset,...] [out=results/loop/robust] [rerender=true]
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import sys
import time

import jax
import numpy as np
from scipy import stats as sps

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import robust_scenario as rs  # noqa: E402

from jaxcal.atomic import write_atomic  # noqa: E402
from jaxcal.diagnosis.effects import build_library, natural_scale  # noqa: E402
from jaxcal.diagnosis.fitting import ModelSpec, fit_model  # noqa: E402
from jaxcal.diagnosis.pipeline import LoopConfig, diagnose  # noqa: E402
from jaxcal.diagnosis.prepare import prepare_data  # noqa: E402
from jaxcal.diagnosis.report import json_safe  # noqa: E402
from jaxcal.models import load  # noqa: E402
from jaxcal.models.turbofan_scenario import STUDY_OUTPUTS  # noqa: E402
from jaxcal.precision import enable_compilation_cache, enable_x64  # noqa: E402
from jaxcal.settings import parse_overrides  # noqa: E402

KINDS = ("parameter", "t2_offset", "sensor_bias", "sensor_gain", "sensor_drift",
         "sensor_gain_drift")  # fmt: skip
LAYERS = KINDS[2:]


@dataclasses.dataclass(frozen=True)
class RobustConfig:
    seeds: int = 4  # records per (kind, multiple)
    clean: int = 20  # clean records (false alarms)
    seed: int = 0
    multiples: tuple[float, ...] = (0.5, 1.0, 2.0, 5.0, 10.0)
    kinds: tuple[str, ...] = KINDS
    declared: tuple[str, ...] = ("HPT_eff_mod",)
    engine: str = "cmapss"
    noise_known: bool = False  # give the diagnosis the true marginal noise std
    sensors: tuple[str, ...] = STUDY_OUTPUTS  # recorded outputs (fewer for tests)
    max_units: int = rs.U_MAX  # record size bounds (smaller for tests)
    max_life: int = rs.C_MAX
    out: str = "results/loop/robust"
    rerender: bool = False  # only rewrite study.json, figure and README from records


def _targets(model, kind, cfg):
    if kind == "parameter":
        return [p for p in model.parameter_names if p not in cfg.declared]
    return list(cfg.sensors) if kind in LAYERS else [kind]


def _probe(model, kind, target, std, level, sensors):
    """A small size in the effect's physical units (the fit stays linear)."""
    s = sensors.index(target) if kind in LAYERS else 0
    if kind in ("sensor_bias", "sensor_drift"):
        return float(std[s])
    if kind in ("sensor_gain", "sensor_gain_drift"):
        return float(std[s] / level[s])
    return (
        -natural_scale(model, target)
        if kind == "parameter"
        else natural_scale(model, target)
    )


def detectability(model, cfg: RobustConfig, loop: LoopConfig) -> dict:
    """``{kind: {target: s1}}`` (module docstring), physical units, magnitudes."""
    ref = rs.reference_setting(len(cfg.sensors), cfg.max_life)
    key = jax.random.key(cfg.seed)
    base, std = rs.make_record(model, ref, "none", "", 0.0, key, cfg.sensors,
                               cfg.declared, noise=False)  # fmt: skip
    level = np.abs(base.x).mean(0)
    noise = dict(zip(cfg.sensors, std.tolist(), strict=True))
    out = {}
    for kind in cfg.kinds:
        out[kind] = {}
        for target in _targets(model, kind, cfg):
            p = _probe(model, kind, target, std, level, cfg.sensors)
            data, _ = rs.make_record(model, ref, kind, target, p, key, cfg.sensors,
                                     cfg.declared, noise=False)  # fmt: skip
            ld = prepare_data(data, model, noise_std=noise, knots=loop.knots,
                              candidate_knots=loop.candidate_knots)  # fmt: skip
            null = fit_model(
                model, ld, ModelSpec(cfg.declared), max_iters=loop.max_iters
            )
            lib = build_library(model, cfg.declared, ld.sensor_names, ld.noise_std,
                                np.abs(ld.x).mean(0))  # fmt: skip
            df = ld.num_units * ld.num_candidate_knots if kind == "parameter" else 1
            n = null.num_resid
            tests = (
                len(lib) + loop.identify.pair_top
            )  # singles + at most pair_top pairs
            lr_star = max(
                loop.identify.bic_margin + df * np.log(n),
                float(sps.chi2.isf(loop.identify.alpha / tests, df)),
            )
            out[kind][target] = abs(p) * float(np.sqrt(lr_star / max(null.ssr, 1e-300)))
            print(f"detectability {kind:18s} {target:14s} {out[kind][target]:.4g}",
                  flush=True)  # fmt: skip
    return out


def run_one(model, cfg, loop, s1, kind, m_idx, seed) -> dict:
    """Draw, generate and diagnose one record; the facts the summary needs."""
    k_idx = -1 if kind == "none" else KINDS.index(kind)
    tag = [cfg.seed, k_idx + 1, m_idx, seed]
    rng = np.random.default_rng(tag)
    setting = rs.draw_setting(rng, len(cfg.sensors), cfg.max_units, cfg.max_life)
    multiple = 0.0 if kind == "none" else cfg.multiples[m_idx]
    target, size, name = "", 0.0, ""
    if kind != "none":
        target = str(rng.choice(_targets(model, kind, cfg)))
        sign = -1.0 if kind == "parameter" else float(rng.choice([-1.0, 1.0]))
        size = sign * multiple * s1[kind][target]
        name = kind if kind == "t2_offset" else f"{kind}[{target}]"
    key = jax.random.key(int(np.random.default_rng(tag).integers(2**31)))
    start = time.time()
    data, std = rs.make_record(model, setting, kind, target, size, key, cfg.sensors,
                               cfg.declared)  # fmt: skip
    noise = (
        dict(zip(cfg.sensors, std.tolist(), strict=True)) if cfg.noise_known else None
    )
    res = diagnose(data, model, cfg.declared, loop, noise_std=noise)
    added = [a for a in res.added if a != "discrepancy"]
    flagged = []
    for eff in res.unit_effects:
        if eff.name == name:
            pairs = zip(res.data.unit_ids, eff.carries, strict=True)
            flagged = [int(u) for u, c in pairs if c]
    return {
        "kind": kind, "multiple": multiple, "seed": seed, "target": target,
        "name": name, "size": size, "s1": s1[kind][target] if kind != "none" else None,
        "setting": setting._asdict(), "rows": int(data.w.shape[0]),
        "verdict": res.verdict, "added": added, "confounded": list(res.confounded),
        "first": bool(kind != "none" and added == [name]),
        "in_confounded_set": name in res.confounded,
        "units": list(res.data.unit_ids.tolist()), "carriers": list(setting.carriers),
        "flagged": flagged, "seconds": time.time() - start,
    }  # fmt: skip


def _rate(values):
    return float(np.mean(values)) if len(values) else None


def summarize(rows: list[dict], cfg: RobustConfig) -> dict:
    """Rates per kind and multiple, the false-alarm rate and the unit-level rates."""
    out = {"kinds": {}}
    for kind in cfg.kinds:
        per = {}
        for m in cfg.multiples:
            rs_ = [r for r in rows if r["kind"] == kind and r["multiple"] == m]
            hits = [u in r["flagged"] for r in rs_ for u in r["carriers"]]
            added = [r for r in rs_ if r["first"] or r["name"] in r["added"]]
            false_flags = [u in r["flagged"] for r in added for u in r["units"]
                           if u not in r["carriers"]]  # fmt: skip
            per[str(m)] = {
                "n": len(rs_),
                "identified": _rate([r["first"] for r in rs_]),
                "in_confounded_set": _rate([r["in_confounded_set"] for r in rs_]),
                "first_or_confounded": _rate(
                    [r["first"] or r["in_confounded_set"] for r in rs_]
                ),
                "missed": _rate([not r["added"] for r in rs_]),
                "unit_hit": _rate(hits), "unit_n": len(hits),
                "unit_false_flag": _rate(false_flags), "unit_false_n": len(false_flags),
            }  # fmt: skip
        out["kinds"][kind] = per
    clean = [r for r in rows if r["kind"] == "none"]
    out["false_alarm"] = _rate([r["verdict"] != "none" for r in clean])
    out["false_alarm_n"] = len(clean)
    alarms = [r for r in clean if r["verdict"] != "none"]
    out["false_alarm_verdicts"] = [
        f"{r['verdict']}:{'+'.join(r['added'])}" for r in alarms
    ]
    eff = [r for r in rows if r["kind"] != "none"]
    for key, sel in (
        ("unit_hit", lambda r: r["multiple"] >= 2.0),
        ("unit_hit_all", None),
    ):
        rr = [r for r in eff if sel is None or sel(r)]
        out[key] = _rate([u in r["flagged"] for r in rr for u in r["carriers"]])
    rr = [r for r in eff if r["multiple"] >= 2.0 and r["name"] in r["added"]]
    out["unit_false_flag"] = _rate(
        [u in r["flagged"] for r in rr for u in r["units"] if u not in r["carriers"]]
    )
    # what the randomisation costs: white vs AR(1) noise, all vs some units carrying
    big = [r for r in eff if r["multiple"] >= 2.0]
    splits = {
        "white": lambda r: r["setting"]["phi"] == 0.0,
        "ar1": lambda r: r["setting"]["phi"] > 0.0,
        "all_carry": lambda r: len(r["carriers"]) == len(r["units"]),
        "some_carry": lambda r: len(r["carriers"]) < len(r["units"]),
    }
    out["breakdown"] = {
        name: {
            "identified_ge2x": _rate([r["first"] for r in big if f(r)]),
            "n_ge2x": sum(1 for r in big if f(r)),
            "false_alarm": _rate([r["verdict"] != "none" for r in clean if f(r)]),
            "n_clean": sum(1 for r in clean if f(r)),
        }
        for name, f in splits.items()
    }
    return out


def plot(summary: dict, cfg: RobustConfig) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    ms = list(cfg.multiples)
    for kind, per in summary["kinds"].items():
        for ax, key in zip(axes, ("identified", "unit_hit"), strict=True):
            ys = [per[str(m)][key] for m in ms]
            ax.plot(ms, [np.nan if y is None else y for y in ys], "o-", label=kind)
    fa = summary["false_alarm"]
    if fa is not None:
        axes[0].axhline(fa, color="k", ls="--", label=f"false alarm (clean) {fa:.2f}")
    for ax, title in zip(axes, ("identification rate (added effect = truth)",
                                "unit-level hit rate (carrier units flagged)"),
                         strict=True):  # fmt: skip
        ax.set_xscale("log")
        ax.set_xticks(ms, [f"{m:g}x" for m in ms])
        ax.set_xlabel("effect size / detectability size")
        ax.set_title(title, fontsize=10)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def _fmt(v):
    return "–" if v is None else f"{v:.2f}"


def render(summary: dict, cfg: RobustConfig, command: str, minutes: float,
           s1: dict, rows: list[dict]) -> str:  # fmt: skip
    """README.md body (the old study's table is added by hand beside it)."""
    ns = [c["n"] for per in summary["kinds"].values() for c in per.values()]
    n_cell = f"{min(ns)}" if min(ns) == max(ns) else f"{min(ns)}-{max(ns)}"
    lines = [
        "## Detection curves (measured)",
        "",
        f"Command: `{command}` ({minutes:.1f} min wall on this machine, 2 shared "
        f"cores, `nice -n 10`; {n_cell} records per (kind, multiple), "
        f"{summary['false_alarm_n']} clean records; noise "
        f"{'known' if cfg.noise_known else 'estimated by the diagnosis'}).",
        "",
        "![detection curves](detection.png)",
        "",
        "| kind | "
        + " | ".join(f"ident. {m:g}x" for m in cfg.multiples)
        + " | conf. set 2x / 5x / 10x | unit hit 2x / 5x / 10x"
        + " | unit false flag 2x / 5x / 10x |",
        "|---|" + "---|" * (len(cfg.multiples) + 3),
    ]
    for kind, per in summary["kinds"].items():
        three = [per.get(str(m), {}) for m in (2.0, 5.0, 10.0)]
        lines.append(
            f"| {kind} | "
            + " | ".join(_fmt(per[str(m)]["identified"]) for m in cfg.multiples)
            + " | "
            + " / ".join(_fmt(c.get("first_or_confounded")) for c in three)
            + " | "
            + " / ".join(_fmt(c.get("unit_hit")) for c in three)
            + " | "
            + " / ".join(_fmt(c.get("unit_false_flag")) for c in three)
            + " |"
        )
    lines += [
        "",
        f"False-alarm rate on clean records: {_fmt(summary['false_alarm'])} "
        f"(n = {summary['false_alarm_n']}; verdicts: "
        f"{', '.join(summary['false_alarm_verdicts']) or 'all none'}).",
        f"Unit-level hit rate (carrier units flagged for the true effect, sizes >= 2x, "
        f"all kinds): {_fmt(summary['unit_hit'])}; at every size "
        f"{_fmt(summary['unit_hit_all'])}. Unit false-flag rate (non-carriers flagged, "
        f"sizes >= 2x, truth added): {_fmt(summary['unit_false_flag'])}.",
        "",
        "What the randomisation costs (sizes >= 2x, all kinds; clean records):",
        "",
        "| records | identified (n) | false alarm (n clean) |",
        "|---|---|---|",
        *(
            f"| {k} | {_fmt(v['identified_ge2x'])} ({v['n_ge2x']}) | "
            f"{_fmt(v['false_alarm'])} ({v['n_clean']}) |"
            for k, v in summary["breakdown"].items()
        ),  # fmt: skip
        "",
        "Detectability sizes s1 (range over targets, physical units): "
        + "; ".join(
            f"{k} {min(v.values()):.3g}-{max(v.values()):.3g}" for k, v in s1.items()
        )
        + ".",  # fmt: skip
    ]
    misses = [f"{r['name']} {r['multiple']:g}x (seed {r['seed']}) -> "
              f"{' + '.join(r['added']) or r['verdict']}"
              for r in rows if r["kind"] != "none" and r["multiple"] >= 5.0
              and not r["first"]]  # fmt: skip
    if misses:
        lines += ["", "Records at >= 5x where the added effect is not the truth: "
                  + "; ".join(misses) + "."]  # fmt: skip
    return "\n".join(lines) + "\n"


HEADER = """# Closing the loop: a study that cannot flatter itself (detection curves)

The first study (`results/loop/README.md`) draws its records from the settings the
diagnosis is built on. Here every record is drawn from settings it does not assume
(`experiments/robust_scenario.py`):

* flight profiles: one of three families (short-haul, the default N-CMAPSS-like one,
  long-haul; different flight times, cruise levels, thrust and day temperatures), each
  unit's flight class random;
* record length: 2-5 units, each life 30-110 cycles, 1-3 samples kept per flight,
  every cycle or every other one;
* the declared modifier's wear (HPT_eff_mod): linear, exponential or piecewise-linear
  with a knee, per unit, end value in the ground-truth range; an undeclared parameter
  effect follows its own random shape per unit;
* noise: level 0.5x-2x the reference (log-uniform) with a 0.8x-1.25x jitter per sensor,
  colour AR(1) along each unit's rows (white in a third of the records, else
  coefficient 0.3-0.8, marginal std kept); the diagnosis *estimates* the noise levels;
* units: the effect is carried by a random subset of 1 to all units (the others clean).

Effect sizes are multiples of a **detectability size** s1, computed, not tuned: on the
nominal reference record (3 units of 80 cycles, 2 samples per flight, linear wear,
white noise at the reference level, every unit carrying), the noise-free record with
the effect at a small probe size p is fitted with the declared parameter only; the SSR
left, in noise std, is the energy E of the part of the effect's signature the declared
parameter cannot absorb, and s1 = p sqrt(LR* / E) with LR* the likelihood-ratio
statistic the diagnosis needs to call a single candidate found (identify.py):
max(bic_margin + df ln n, chi2_df quantile at alpha / number of tests); df = 1 for a
constant effect, units x candidate knots for an undeclared parameter. At 1x the
expected statistic of the truth equals the threshold on the reference record.

Rates: **identified** = the diagnosis adds exactly the true effect (the old study's
"first"); **conf. set** = identified or the truth in the reported confounded set;
**unit hit** = carrier units flagged by the per-unit verdict (`carries`, Holm z-test,
jaxcal/diagnosis/units.py) for the true effect (0 when the truth is not added);
**unit false flag** = non-carrier units flagged, in records where the truth was added;
**false alarm** = a clean record whose verdict is not `none`.

"""


def _old_table(path="results/loop/README.md") -> str:
    """The first study's table and summary lines, for comparison."""
    if not os.path.exists(path):
        return ""
    lines = open(path).read().splitlines()
    groups = [[ln for ln in lines if ln.startswith(p)]
              for p in ("Command:", "|", ("Library kinds", "False-alarm"))]  # fmt: skip
    return "\n## The first study, for comparison (results/loop/README.md)\n\n" + (
        "\n\n".join("\n".join(g) for g in groups) + "\n"
    )


def _write(cfg, rows, s1, command, minutes):
    summary = summarize(rows, cfg)
    payload = {"config": dataclasses.asdict(cfg), "command": command,
               "minutes": minutes, "detectability": s1, "summary": summary}  # fmt: skip
    write_atomic(os.path.join(cfg.out, "study.json"),
                 json.dumps(json_safe(payload), indent=1) + "\n")  # fmt: skip
    write_atomic(os.path.join(cfg.out, "detection.png"), plot(summary, cfg))
    text = render(summary, cfg, command, minutes, s1, rows)
    write_atomic(os.path.join(cfg.out, "README.md"), HEADER + text + _old_table())
    return text


def main(argv: list[str]) -> int:
    try:
        cfg = parse_overrides(argv, RobustConfig())
        bad = [k for k in cfg.kinds if k not in KINDS]
        if bad:
            raise ValueError(f"kinds: unknown {bad}; valid: {', '.join(KINDS)}")
    except ValueError as err:
        print(f"loop_robust: {err}", file=sys.stderr)
        return 2
    os.makedirs(cfg.out, exist_ok=True)
    rec_path = os.path.join(cfg.out, "records.jsonl")
    s1_path = os.path.join(cfg.out, "detectability.json")
    rows = []
    if os.path.exists(rec_path):
        with open(rec_path) as f:
            rows = [json.loads(line) for line in f if line.strip()]
    command = "python experiments/loop_robust.py " + " ".join(argv)
    if cfg.rerender:
        if not os.path.exists(os.path.join(cfg.out, "study.json")):
            print(f"loop_robust: rerender needs {cfg.out}/study.json", file=sys.stderr)
            return 2
        with open(os.path.join(cfg.out, "study.json")) as f:
            old = json.load(f)
        print(_write(cfg, rows, old["detectability"], old["command"], old["minutes"]))
        return 0
    enable_x64()
    enable_compilation_cache()
    model, loop = load(cfg.engine), LoopConfig()
    start = time.time()
    if os.path.exists(s1_path):
        with open(s1_path) as f:
            s1 = json.load(f)
    else:
        s1 = detectability(model, cfg, loop)
        write_atomic(s1_path, json.dumps(s1, indent=1) + "\n")
    done = {(r["kind"], r["multiple"], r["seed"]) for r in rows}
    # seed-major, so that a stopped run covers every cell evenly
    cells = [
        cell for s in range(max(cfg.seeds, cfg.clean))
        for cell in ([("none", 0, s)] if s < cfg.clean else []) + (
            [(k, i, s) for k in cfg.kinds for i in range(len(cfg.multiples))]
            if s < cfg.seeds else [])
    ]  # fmt: skip
    for n, (kind, m_idx, seed) in enumerate(cells):
        mult = 0.0 if kind == "none" else cfg.multiples[m_idx]
        if (kind, mult, seed) in done:
            continue
        row = run_one(model, cfg, loop, s1, kind, m_idx, seed)
        rows.append(row)
        with open(rec_path, "a") as f:  # one line per record: the run resumes
            f.write(json.dumps(json_safe(row)) + "\n")
        print(f"[{n + 1}/{len(cells)}] {kind:17s} {mult:4g}x seed {seed}: "
              f"{row['verdict']:22s} added {row['added']} truth {row['name']} "
              f"carriers {row['carriers']} flagged {row['flagged']} "
              f"({row['rows']} rows, {row['seconds']:.1f} s)", flush=True)  # fmt: skip
    minutes = (time.time() - start) / 60.0
    study = os.path.join(cfg.out, "study.json")
    if os.path.exists(study):  # a resumed run: the sessions' wall times add up
        with open(study) as f:
            minutes += json.load(f)["minutes"]
    print(_write(cfg, rows, s1, command.strip(), minutes))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
