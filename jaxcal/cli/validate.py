"""``python -m jaxcal.validate``: every check of design/engine.md, measured.

Prints one line per check (measured number, threshold, PASS/FAIL) and writes the full
numbers as JSON (default ``results/engine/validation_<engine>.json``; ``out=PATH`` to
change, ``engine=agtf30`` for the other configuration, ``quick=true`` for a coarser
envelope grid; the flag spellings ``--out PATH``, ``--engine agtf30`` and ``--quick``
work too).
Exit status 1 when any check fails. Checks: conservation, FD002 table, FD001 HPC
signature, HPT-efficiency signature, envelope convergence (and rejection outside it),
DS02 ranges, gradients vs finite differences, Jacobian rank and condition number, plus
the AGTF30 operating points for that configuration.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.cli.args import flags_as_overrides, parse_command_line
from jaxcal.models.turbofan.physics import reference as ref
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.audit import audit_point
from jaxcal.models.turbofan.physics.constants import MEASURED_SENSOR_NAMES, SENSOR_NAMES
from jaxcal.models.turbofan.physics.engine import Engine, load_engine
from jaxcal.models.turbofan.physics.guess import tra_for_pcn
from jaxcal.precision import enable_x64
from jaxcal.runs.atomic import write_atomic
from jaxcal.settings import check_output_path, parse_overrides

S = {n: i for i, n in enumerate(SENSOR_NAMES)}


def _check(name, value, threshold, passed, **details):
    return {"check": name, "value": value, "threshold": threshold,
            "passed": bool(passed), **details}  # fmt: skip


def _w(rows):
    rows = np.asarray(rows, dtype=float)
    t2 = np.asarray(isa_total_temperature(rows[:, 0], rows[:, 1])) + rows[:, 3]
    return np.stack([rows[:, 0], rows[:, 1], rows[:, 2], t2], 1)


def check_conservation(engine: Engine, f) -> dict:
    rng = np.random.default_rng(0)
    n = 256
    w = _w(np.stack([rng.uniform(0, 42000, n), rng.uniform(0, 0.85, n),
                     rng.uniform(20, 100, n), rng.uniform(-30, 40, n)], 1))  # fmt: skip
    th = np.zeros((n, 10))
    th[:, 4:] = rng.uniform(-0.04, 0.0, (n, 6))
    x, info = f(w, th)
    audit = jax.jit(
        jax.vmap(lambda a, b, z: audit_point(engine.design, a, b, jnp.zeros(6), z))
    )
    a = audit(w, th, info.z)
    conv = np.asarray(info.converged)
    worst = {k: float(np.max(np.asarray(v)[conv])) for k, v in a._asdict().items()}
    value = max(worst.values())
    return _check("conservation (max relative imbalance)", value, 1e-8, value <= 1e-8,
                  per_balance=worst, points=int(conv.sum()))  # fmt: skip


def check_fd002(f) -> dict:
    x, info = f(ref.FD002_CONDITIONS, np.zeros((6, 10)))
    x = np.asarray(x)
    table = {}
    errs = []
    for s in ref.FD002_CHECKED_SENSORS:
        e = 100.0 * (x[:, S[s]] / np.asarray(ref.FD002_EARLY_MEANS[s]) - 1.0)
        table[s] = [round(float(v), 3) for v in e]
        errs.extend(np.abs(e))
    med, mx = float(np.median(errs)), float(np.max(errs))
    return _check("FD002 six conditions: |error| % (median / max)",
                  [med, mx], [1.0, 3.0],
                  med <= 1.0 and mx <= 3.0 and bool(np.all(info.converged)),
                  error_pct_per_sensor_condition=table)  # fmt: skip


def check_fd001(f) -> dict:
    names = list(ref.FD001_HPC_SIGNATURE)
    tgt = np.array([ref.FD001_HPC_SIGNATURE[n] for n in names])
    w0 = np.tile(ref.FD001_CONDITION, (3, 1))
    th = np.zeros((3, 10))
    th[1, 4] = th[2, 5] = -0.01
    x, _ = f(w0, th)
    x = np.asarray(x)
    idx = [S[n] for n in names]
    sens = np.stack(
        [(x[1, idx] - x[0, idx]) / -0.01, (x[2, idx] - x[0, idx]) / -0.01], 1
    )
    # weighted least squares for (HPC_eff, HPC_flow), clipped to the box [-0.05, 0]
    pair, *_ = np.linalg.lstsq(sens / np.abs(tgt)[:, None], np.sign(tgt), rcond=None)
    pair = np.clip(pair, -0.05, 0.0)
    th_fit = np.zeros((2, 10))
    th_fit[1, 4:6] = pair
    xf, _ = f(np.tile(ref.FD001_CONDITION, (2, 1)), th_fit)
    xf = np.asarray(xf)
    model = xf[1, idx] - xf[0, idx]
    ratio = model / tgt
    ok = bool(
        np.all(np.sign(model) == np.sign(tgt)) and np.all(np.abs(ratio - 1) <= 0.3)
    )
    return _check("FD001 HPC signature: worst |model/data - 1|",
                  float(np.max(np.abs(ratio - 1))), 0.3, ok,
                  fitted_pair={"HPC_eff_mod": float(pair[0]),
                               "HPC_flow_mod": float(pair[1])},
                  model=dict(zip(names, model.round(4).tolist(), strict=False)),
                  data=ref.FD001_HPC_SIGNATURE)  # fmt: skip


def check_hpt_signature(f) -> dict:
    g = np.array(list(itertools.product([10000.0, 25000.0, 35000.0], [0.3, 0.55, 0.8],
                                        [60.0, 80.0, 100.0], [0.0])))  # fmt: skip
    w = _w(g)
    th = np.zeros((len(w), 10))
    th1 = th.copy()
    th1[:, 6] = -0.01
    xa, ia = f(w, th)
    xb, ib = f(w, th1)
    xa, xb = np.asarray(xa), np.asarray(xb)
    model = {
        "T48": float(np.mean(xb[:, S["T48"]] - xa[:, S["T48"]])),
        "T50": float(np.mean(xb[:, S["T50"]] - xa[:, S["T50"]])),
        "Nc": float(np.mean(xb[:, S["Nc"]] - xa[:, S["Nc"]])),
        "Wf_pct": float(np.mean(100 * (xb[:, S["Wf"]] / xa[:, S["Wf"]] - 1))),
    }
    ratios = {k: model[k] / v for k, v in ref.HPT_EFF_SIGNATURE.items()}
    ok = all(0.5 <= r <= 2.0 for r in ratios.values())
    worst = max(max(r, 1 / r) if r > 0 else np.inf for r in ratios.values())
    return _check("HPT_eff -1 %: worst factor vs pyCycle", float(worst), 2.0,
                  ok and bool(np.all(ia.converged) & np.all(ib.converged)),
                  model=model, reference=ref.HPT_EFF_SIGNATURE)  # fmt: skip


def envelope_grid(quick: bool, alt_max: float = 42000.0, mach_max: float = 0.85):
    """engine.md check 5: alt 0-42 kft, Mach 0-0.85 (clipped to the configuration's own
    envelope), TRA 20-100, T2 ISA -30 to +40 degR; theta = 0 and every component alone
    at its bound (-0.06 / +0.02, fan and LPC to -0.25)."""
    n = (4, 4, 5, 3) if quick else (8, 7, 9, 4)
    g = np.array(list(itertools.product(np.linspace(0, alt_max, n[0]),
                                        np.linspace(0, mach_max, n[1]),
                                        np.linspace(20, 100, n[2]),
                                        np.linspace(-30, 40, n[3]))))  # fmt: skip
    lo = np.array([-0.25] * 4 + [-0.06] * 6)
    thetas = [np.zeros(10)]
    for j in range(10):
        for v in (lo[j], 0.02):
            t = np.zeros(10)
            t[j] = v
            thetas.append(t)
    return _w(g), np.array(thetas)


def check_envelope(engine: Engine, f, quick: bool) -> list[dict]:
    env = engine.envelope
    w, thetas = envelope_grid(
        quick, min(42000.0, env.alt_ft[1]), min(0.85, env.mach[1])
    )
    conv = []
    worst_iters = 0
    for t in thetas:
        _, info = f(w, np.tile(t, (len(w), 1)))
        conv.append(np.asarray(info.converged))
        worst_iters = max(worst_iters, int(np.max(info.iterations)))
    conv = np.stack(conv)
    # random sparse faults: 1-3 components anywhere in the box, as real faults come
    rng = np.random.default_rng(1)
    lo = np.array([-0.25] * 4 + [-0.06] * 6)
    th_r = np.zeros((len(w), 10))
    for i in range(len(w)):
        js = rng.choice(10, size=rng.integers(1, 4), replace=False)
        th_r[i, js] = rng.uniform(lo[js], 0.02)
    _, info_r = f(w, th_r)
    frac_r = float(np.mean(info_r.converged))
    frac = float(conv.mean())
    out = [_check("envelope grid: fraction converged (theta = 0 and every component at "
                  "its bounds)", frac, 1.0, frac == 1.0, points=int(conv.size),
                  max_iterations=worst_iters),  # fmt: skip
           _check("envelope grid: fraction converged (random 1-3 component faults)",
                  frac_r, 1.0, frac_r == 1.0, points=len(w))]  # fmt: skip
    # outside the envelope: flagged, and the checked entry point names the field
    bad_w = np.array([[60000.0, 0.8, 80.0, 400.0], [30000.0, 1.5, 80.0, 500.0],
                      [30000.0, 0.7, 150.0, 430.0], [np.nan, 0.7, 80.0, 430.0],
                      [30000.0, 0.7, 80.0, 600.0]])  # fmt: skip
    bad_th = np.zeros((6, 10))
    bad_th[5, 6] = -0.5
    ws = np.concatenate([bad_w, [[30000.0, 0.7, 80.0, 430.0]]])
    _, info_b = f(ws, bad_th)
    flagged = bool(not np.any(info_b.converged))
    messages = []
    for i in range(len(ws)):
        try:
            engine.evaluate_checked(ws[i], bad_th[i])
            messages.append(None)
        except ValueError as err:
            messages.append(str(err))
    named = all(
        m is not None and ("w[..., '" in m or "theta[..., '" in m) for m in messages
    )
    out.append(_check("outside the envelope: converged is False and evaluate_checked "
                      "names the field", flagged and named, True, flagged and named,
                      messages=messages))  # fmt: skip
    return out


def check_ds02(f) -> dict:
    """Phase-sampled operating points of DS02-like flights (alt 10-35 kft,
    Mach 0.26-0.75, TRA 24-88): climb, cruise and descent relations between alt, Mach
    and TRA."""
    rng = np.random.default_rng(2)
    n = 1200
    phase = rng.integers(0, 3, n)
    alt = np.where(
        phase == 1, rng.uniform(25000, 35000, n), rng.uniform(10000, 35000, n)
    )
    mach = np.where(phase == 1, rng.uniform(0.65, 0.75, n),
                    0.26 + (0.74 - 0.26) * (alt - 10000) / 25000
                    + rng.uniform(-0.05, 0.05, n))  # fmt: skip
    tra = np.select([phase == 0, phase == 1],
                    [rng.uniform(72, 88, n), rng.uniform(55, 80, n)],
                    rng.uniform(24, 40, n))  # fmt: skip
    w = _w(np.stack([alt, np.clip(mach, 0.26, 0.75), tra, rng.uniform(-25, 25, n)], 1))
    x, info = f(w, np.zeros((n, 10)))
    x = np.asarray(x)
    worst = 0.0
    ranges = {}
    for s, (lo, hi) in ref.DS02_RANGES.items():
        v = x[:, S[s]]
        ranges[s] = {"model": [float(v.min()), float(v.max())], "ds02": [lo, hi]}
        worst = max(worst, lo / v.min() - 1 if v.min() < lo else 0.0,
                    v.max() / hi - 1 if v.max() > hi else 0.0)  # fmt: skip
    ok = worst <= 0.15 and bool(np.all(info.converged))
    return _check("DS02 envelope: worst excursion beyond the DS02 ranges", float(worst),
                  0.15, ok, ranges=ranges, points=n)  # fmt: skip


def check_gradients(engine: Engine) -> list[dict]:
    """jacfwd (implicit-function gradients) vs central differences, and identifiability.

    Identifiability: at a single operating point the 14 measured sensors can never fix
    all of HPT_eff, HPT_flow, LPT_eff and LPT_flow, because P45 (between the turbines)
    is not measured: raising P45 while HPT_eff, LPT_eff and LPT_flow compensate keeps
    every measured station unchanged (capacity and power of both turbines are four
    equations in those modifiers and one free pressure). This holds for any 0-D cycle,
    so the check is made the way calibration uses data: on a cruise segment (four cruise
    points), where the null direction of one point is seen by the others. The
    single-point rank with and without P45 is reported too.
    """
    th0 = jnp.full(10, -0.005)
    cruise = [(35000.0, 0.78, 85.0), (35000.0, 0.78, 75.0), (33000.0, 0.74, 80.0),
              (31000.0, 0.72, 70.0)]  # fmt: skip
    ws = jnp.array(
        [[a, m, t, float(isa_total_temperature(a, m))] for a, m, t in cruise]
    )
    w0 = ws[0]

    def xs(w, th):
        return engine.evaluate(w, th)[0]

    jt = np.asarray(jax.jit(jax.jacfwd(xs, argnums=1))(w0, th0))
    jw = np.asarray(jax.jit(jax.jacfwd(xs, argnums=0))(w0, th0))
    f = jax.jit(xs)
    h_th = 1e-6
    fd_t = np.stack([(np.asarray(f(w0, th0.at[j].add(h_th)))
                      - np.asarray(f(w0, th0.at[j].add(-h_th))))
                     / (2 * h_th) for j in range(10)], 1)  # fmt: skip
    h_w = np.array([1.0, 1e-5, 1e-4, 1e-3])
    fd_w = np.stack([(np.asarray(f(w0.at[j].add(h_w[j]), th0))
                      - np.asarray(f(w0.at[j].add(-h_w[j]), th0)))
                     / (2 * h_w[j]) for j in range(4)], 1)  # fmt: skip

    def rel(a, b):
        # entries relative to themselves, floored at 1e-4 of their sensor's largest
        # entry (sensors the controller holds, Nf, have exactly zero derivative rows)
        floor = (1e-4 * np.max(np.abs(b), axis=1, keepdims=True)
                 + 1e-12 * np.max(np.abs(b)))  # fmt: skip
        return float(np.max(np.abs(a - b) / (np.abs(b) + floor)))

    e_t, e_w = rel(jt, fd_t), rel(jw, fd_w)

    def normalised(w):
        x = np.asarray(f(w, th0))
        j = np.asarray(jax.jit(jax.jacfwd(xs, argnums=1))(w, th0))
        # sensors relative, parameters in 1 % steps
        return j / np.abs(x)[:, None] * 0.01

    def rank_cond(j):
        sv = np.linalg.svd(j, compute_uv=False)
        return int(np.sum(sv > sv[0] * 1e-9)), float(sv[0] / sv[-1])

    jn = [normalised(w) for w in ws]
    ms = np.array([S[n] for n in MEASURED_SENSOR_NAMES])
    single = rank_cond(jn[0][ms])
    with_p45 = rank_cond(jn[0][np.append(ms, S["P45"])])
    segment = rank_cond(np.concatenate([j[ms] for j in jn]))
    return [
        _check("gradients: jacfwd vs central differences, max relative error "
               "(theta / w)", [e_t, e_w], 1e-5, max(e_t, e_w) <= 1e-5),
        _check("identifiability: rank of d(14 sensors)/d(10 theta) on a cruise "
               "segment (condition number)", segment[0], 10, segment[0] == 10,
               condition_number=segment[1], single_point_rank=single[0],
               single_point_rank_with_P45=with_p45[0],
               single_point_condition_with_P45=with_p45[1]),
    ]  # fmt: skip


def check_agtf30(engine: Engine, f) -> dict:
    errs = {}
    for name, pt in ref.AGTF30_POINTS.items():
        alt, mach, pcn, t2 = pt["w"]
        w = np.array([alt, mach, float(tra_for_pcn(engine.design, pcn)), t2])
        x, _ = f(w[None], np.zeros((1, 10)))
        x = np.asarray(x)[0]
        errs[name] = {s: round(100 * (x[S[s]] / v - 1), 3)
                      for s, v in pt["values"].items() if s != "T2"}  # fmt: skip
    allv = np.abs([v for d in errs.values() for v in d.values()])
    med, mx = float(np.median(allv)), float(np.max(allv))
    return _check("AGTF30 cruise / take-off points: |error| % (median / max)",
                  [med, mx], "reported", True, error_pct=errs)  # fmt: skip


def run(engine_name: str, quick: bool) -> dict:
    engine = load_engine(engine_name)
    f = jax.jit(engine.evaluate)
    t0 = time.time()
    checks = [check_conservation(engine, f)]
    if engine_name == "cmapss":
        checks += [check_fd002(f), check_fd001(f), check_hpt_signature(f)]
    else:
        checks += [check_agtf30(engine, f)]
    checks += check_envelope(engine, f, quick)
    if engine_name == "cmapss":
        checks.append(check_ds02(f))
    checks += check_gradients(engine)
    return {"engine": engine_name, "seconds": time.time() - t0,
            "all_passed": all(c["passed"] for c in checks),
            "checks": checks}  # fmt: skip


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return " / ".join(_fmt(x) for x in v)
    return str(v)


USAGE = (
    "usage: python -m jaxcal.validate [engine=cmapss|agtf30] [out=PATH] [quick=true]"
    "  (or --engine X --out PATH --quick)"
)


@dataclasses.dataclass(frozen=True)
class ValidateArgs:
    """Which engine to check and where the numbers go."""

    engine: Literal["cmapss", "agtf30"] = "cmapss"
    out: str | None = None  # default results/engine/validation_<engine>.json
    quick: bool = False  # a coarser envelope grid


def parse_args(argv: list[str]) -> ValidateArgs:
    """The :class:`ValidateArgs` of a command line (the one ``key=value`` grammar,
    the documented flags as its spellings).

    Raises:
        ValueError: a bad key, flag or value (named).
    """
    flags = {"--engine": "engine", "--out": "out", "--quick": "quick"}
    tokens = flags_as_overrides(argv, flags, switches=("--quick",))
    args = parse_overrides(tokens, ValidateArgs())
    if args.out is not None:  # refused now, not after the checks
        check_output_path(args.out, "out")
    return args


def main(argv=None) -> int:
    args, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if args is None:
        return code
    enable_x64()
    result = run(args.engine, args.quick)
    for c in result["checks"]:
        flag = "PASS" if c["passed"] else "FAIL"
        print(
            f"[{flag}] {c['check']}: {_fmt(c['value'])} "
            f"(threshold {_fmt(c['threshold'])})"
        )
    out = Path(args.out or f"results/engine/validation_{args.engine}.json")
    write_atomic(out, json.dumps(result, indent=1, default=float))
    print(f"{'all checks passed' if result['all_passed'] else 'SOME CHECKS FAILED'} "
          f"({result['seconds']:.0f} s); details in {out}")  # fmt: skip
    return 0 if result["all_passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
