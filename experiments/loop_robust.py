"""Detection curves of the closing-the-loop diagnosis on data it does not assume,
on three models: the turbofan, the heat exchanger and a model with memory.

Every record is drawn by :mod:`robust_scenario` (random operating patterns, lives and
sampling, wear shapes, noise level and AR(1) colour, number of units, which of them
carry the effect and, for a step, from when), the noise levels and colour are
*estimated* by the diagnosis, and the effect size is a multiple of the record's
**detectability size** ``s1``: on the record's own noise-free data, with the effect at
size ``s`` on its carriers, the declared parameters are fitted alone under the
record's true noise model (level and colour, prewhitened); the SSR left, minus the SSR
left without the effect, is the energy ``E(s)`` of the part of the effect's signature
that the declared parameters cannot absorb, and ``s1`` solves ``E(s1) = LR*`` (secant
steps in ``log s`` from a small probe; a linear effect needs one) with ``LR*`` what the
diagnosis needs to call the true
effect, in its true form, found (identify.py): ``max(bic_margin + k ln n + 2 ln C(U,
m), chi2_k^-1(1 - alpha / tests))`` with ``k`` the parameters of the form (one for a
fleet-wide constant or drift when every unit carries it; per carrier one, the
candidate knots of a smoothly changing parameter, two for a step with its onset) and
``m`` the carriers. At 1x the expected likelihood-ratio statistic of the truth equals
the threshold on that record, whatever its noise colour, length or number of
carriers. (The study before issue 24 computed one ``s1`` per kind on a nominal white-
noise record; its multiples meant far less signal on a coloured record with one
carrier of five.)

Measured per model, kind and multiple: **identification** (the diagnosis names the
true effect, kind and target: it adds exactly that effect, or, where the data cannot
tell two effects apart, its verdict is ``confounded`` and the reported confounded
set holds the truth and the effect it added; the strict rate, exactly the truth
added, is kept beside it), **unit hit rate** (carrier units flagged for the
true effect, or for the effect the verdict added in its place when it named the two
as confounded; 0 when the truth is not named), **onset error** (a step's estimated
onset against the truth, over the carriers flagged, as a share of the carrier's
record length); on clean records the **false-alarm** rate (any verdict but ``none``).

Resumable: one JSON line per record is appended to ``<out>/records.jsonl`` and done
records are skipped. Writes ``<out>/summary.json`` (the issue's keys),
``<out>/study.json``, ``<out>/detection.png`` and ``<out>/README.md``.

Usage::

    python experiments/loop_robust.py [models=turbofan,heat_exchanger,thermal]
        [seeds=16] [clean=48] [multiples=2,5,10] [kinds=...] [out=results/loop/robust]
        [noise_order=3] [forms=fleet,units] [rerender=true] [shards=2 shard=0]
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np
from scipy import stats as sps
from scipy.special import gammaln

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import robust_report  # noqa: E402
import robust_scenario as rs  # noqa: E402
from loop_before import verdict_facts  # noqa: E402

from jaxcal.cache import enable_compilation_cache  # noqa: E402
from jaxcal.diagnosis.data.prepare import prepare_data  # noqa: E402
from jaxcal.diagnosis.data.synthetic import kind_of  # noqa: E402
from jaxcal.diagnosis.fitting.identify import IdentifyConfig  # noqa: E402
from jaxcal.diagnosis.fitting.joint import fit_model  # noqa: E402
from jaxcal.diagnosis.kinds.table import KINDS, natural_scale  # noqa: E402
from jaxcal.diagnosis.kinds.terms import ModelSpec  # noqa: E402
from jaxcal.diagnosis.pipeline import LoopConfig, diagnose  # noqa: E402
from jaxcal.diagnosis.report.write import json_safe  # noqa: E402
from jaxcal.diagnosis.residuals.noise import MAX_ORDER, NoiseModel  # noqa: E402
from jaxcal.models import load  # noqa: E402
from jaxcal.precision import enable_x64  # noqa: E402
from jaxcal.settings import parse_overrides  # noqa: E402


@dataclasses.dataclass(frozen=True)
class RobustConfig:
    models: tuple[str, ...] = tuple(rs.STUDY_MODELS)
    seeds: int = 16  # records per (model, kind, multiple)
    clean: int = 48  # clean records per model (false alarms)
    seed: int = 0
    multiples: tuple[float, ...] = (2.0, 5.0, 10.0)
    kinds: tuple[str, ...] = ()  # restrict (default: every kind of each model)
    noise_known: bool = False  # give the diagnosis the true marginal noise std
    noise_order: int = MAX_ORDER  # the diagnosis's AR order (0: white, a lever)
    forms: tuple[str, ...] = ("fleet", "units")  # the diagnosis's forms (a lever)
    without: tuple[str, ...] = ()  # library kinds left out (a lever: the step kinds)
    max_units: int = rs.U_MAX  # record size bounds (smaller for tests)
    max_life: int = 0  # 0: each model's own
    out: str = "results/loop/robust"
    rerender: bool = False  # only rewrite summary, figure and README from records
    shards: int = 1  # the cells split over processes: this one runs every shards-th
    shard: int = 0  # ... starting at this one (merge the records.jsonl files after)


def loop_config(cfg: RobustConfig) -> LoopConfig:
    library = tuple(k for k in KINDS if k not in cfg.without) if cfg.without else ()
    return LoopConfig(
        noise_order=cfg.noise_order, identify=IdentifyConfig(forms=cfg.forms),
        kinds=library,
    )  # fmt: skip


def targets(model, sm, kind) -> list[str]:
    spec = kind_of(model, kind)
    if spec.channel == "parameter":
        return [p for p in model.parameter_names if p not in sm.declared]
    return list(sm.outputs) if spec.is_sensor else [kind]


def _probe(model, kind, target, std, level, outputs) -> float:
    """A small size in the effect's physical units (the fit stays linear)."""
    spec = kind_of(model, kind)
    if spec.is_sensor:
        s = list(outputs).index(target)
        return float(std[s] / (level[s] if spec.channel == "multiplicative" else 1.0))
    return natural_scale(model, target)


def threshold(spec, n: int, units: int, carriers: int, loop: LoopConfig,
              tests: int) -> float:  # fmt: skip
    """``LR*`` of the true effect in its true form (module docstring)."""
    ident = loop.identify
    if spec.fleet and carriers == units:
        k, sel = 1, 0.0
    else:
        k = spec.num_free(loop.candidate_knots) * carriers
        sel = 2.0 * float(gammaln(units + 1) - gammaln(carriers + 1)
                          - gammaln(units - carriers + 1))  # fmt: skip
    return max(ident.bic_margin + k * np.log(n) + sel,
               float(sps.chi2.isf(ident.alpha / tests, k)))  # fmt: skip


SIZE_STEPS = 4  # secant steps of the detectability size (log-log, in size)
GROW_STEPS = 8  # x4 steps from the probe until the energy is a quarter of LR*


def _null_ssr(model, sm, setting, kind, target, size, seed, loop) -> float:
    """SSR of the declared-only fit of the noise-free record with the effect at
    ``size``, prewhitened by the record's true noise model (level and colour)."""
    data, std, _ = rs.make_record(model, sm, setting, kind, target, size, seed, False)
    noise = dict(zip(sm.outputs, std.tolist(), strict=True))
    ld = prepare_data(data, model, noise_std=noise, knots=loop.knots,
                      candidate_knots=loop.candidate_knots)  # fmt: skip
    num_s = len(ld.sensor_names)
    ar = np.zeros((num_s, MAX_ORDER))
    ar[:, 0] = setting.phi
    true = NoiseModel.white(ld.noise_std, "given")._replace(
        ar=ar, order=np.full(num_s, int(setting.phi > 0))
    )
    ld = ld.with_noise(true)
    spec = ModelSpec(sm.declared, initial_state=model.is_stateful)
    null = fit_model(model, ld, spec, max_iters=loop.max_iters)
    return float(null.ssr), int(null.num_resid)


def detectability(model, sm, setting, kind, target, sign, seed, loop) -> float:
    """The record's ``s1`` (module docstring), physical units, magnitude.

    ``E(s)``, the SSR the declared-only fit leaves on the noise-free record with the
    effect at ``sign * s`` minus what it leaves without it (the declared splines do
    not follow every wear shape exactly), is solved for ``E(s1) = LR*`` by secant
    steps in ``log s``, from a probe grown by 4x until its energy is a quarter of
    ``LR*`` (below that, the fit's own jitter of a few tenths of SSR decides): the
    effect of a parameter is not linear in its size (seen: a heat capacity's step
    left 13x, not 25x, the energy at 5x its probe), and a linear extrapolation from
    a small probe would size it too small. An effect of the measurement layer
    adds to the outputs, and its energy is quadratic in its size: one step.
    """
    clean, std, _ = rs.make_record(model, sm, setting, "none", "", 0.0, seed, False)
    level = np.nanmean(np.abs(clean.x), axis=0)
    probe = abs(_probe(model, kind, target, std, level, sm.outputs))
    base, n = _null_ssr(model, sm, setting, "none", "", 0.0, seed, loop)
    tests = 2 * sum(len(targets(model, sm, k)) for k in sm.kinds) * 2
    lr_star = threshold(kind_of(model, kind), n, setting.units,
                        len(setting.carriers), loop, tests)  # fmt: skip

    def energy(size):
        ssr, _ = _null_ssr(model, sm, setting, kind, target, sign * size, seed, loop)
        return ssr - base

    # grow the size until the energy stands well above the fit's own jitter (the
    # declared fit moves by a few tenths of SSR from one record to the next)
    size, e, prev = probe, energy(probe), None
    for _ in range(GROW_STEPS):
        if e >= lr_star / 4.0:
            break
        # a point below LR* / 16 is mostly jitter: no slope from it
        prev = (np.log(size), np.log(e)) if e > lr_star / 16.0 else None
        size *= 4.0
        e = energy(size)
    if kind_of(model, kind).is_sensor:  # the measurement layer: E is quadratic
        return size * float(np.sqrt(lr_star / max(e, 1e-12)))
    for _ in range(SIZE_STEPS):
        here = (np.log(size), np.log(max(e, 1e-12)))
        slope = 2.0  # quadratic: a linear effect
        if prev is not None and here[0] != prev[0] and e > 0:
            slope = float(np.clip((here[1] - prev[1]) / (here[0] - prev[0]), 0.5, 4.0))
        new = size * float(np.exp((np.log(lr_star) - here[1]) / slope))
        if abs(np.log(new / size)) < 0.05:
            return new
        prev, size = here, new
        e = energy(size)
    return size


def _room(model, target: str, sign: float) -> float:
    """How far a parameter can move from nominal in direction ``sign``."""
    p = model.parameters[model.parameter_names.index(target)]
    return (p.high - p.nominal) if sign > 0 else (p.nominal - p.low)


def _target(model, sm, cfg, loop, kind, setting, record_seed, rng):
    """``(target, sign, s1)``: a random target (and sign) of ``kind``. A parameter's
    change at the largest multiple must stay within half its room to the bound it
    moves towards (a weakly detectable parameter would otherwise be pushed outside
    the model's range); targets are tried in random order until one fits."""
    spec = kind_of(model, kind)
    options = list(targets(model, sm, kind))
    rng.shuffle(options)
    if spec.channel != "parameter":
        target, sign = str(options[0]), float(rng.choice([-1.0, 1.0]))
        return target, sign, detectability(model, sm, setting, kind, target, sign,
                                           record_seed, loop)  # fmt: skip
    best = None
    for target in options:
        if sm.name == "turbofan":
            sign = -1.0  # a health modifier falls as the engine wears
        else:
            sign = (
                1.0 if _room(model, target, 1.0) >= _room(model, target, -1.0) else -1.0
            )
        s1 = detectability(model, sm, setting, kind, target, sign, record_seed, loop)
        share = max(cfg.multiples) * s1 / max(_room(model, target, sign), 1e-300)
        if best is None or share < best[3]:
            best = (str(target), sign, s1, share)
        if share <= 0.5:
            break
    return best[:3]


def draw_record(model, sm, cfg: RobustConfig, loop, kind, m_idx, seed):
    """Draw, size and generate one record (no diagnosis).

    Returns:
        ``(data, std, onsets, meta)``: the Dataset, the true noise std per output,
        the onset cycle per carrier and the record's facts (the row's first keys).
    """
    models, kinds = list(rs.STUDY_MODELS), ["none", *sm.kinds]
    tag = [cfg.seed, models.index(sm.name), kinds.index(kind), m_idx, seed]
    rng = np.random.default_rng(tag)
    setting = rs.draw(sm, rng, cfg.max_units, cfg.max_life or None)
    multiple = 0.0 if kind == "none" else cfg.multiples[m_idx]
    target, size, name, s1 = "", 0.0, "", None
    record_seed = int(rng.integers(2**31))
    if kind != "none":
        target, sign, s1 = _target(model, sm, cfg, loop, kind, setting, record_seed,
                                   rng)  # fmt: skip
        size = sign * multiple * s1
        name = kind_of(model, kind).candidate_name(target)
    data, std, onsets = rs.make_record(model, sm, setting, kind, target, size,
                                       record_seed)  # fmt: skip
    meta = {
        "model": sm.name, "kind": kind, "multiple": multiple, "seed": seed,
        "target": target, "name": name, "size": size, "s1": s1,
        "setting": setting._asdict(), "rows": int(data.num_rows),
        "carriers": list(setting.carriers),
        "onsets": {str(k): v for k, v in onsets.items()},
    }  # fmt: skip
    return data, std, onsets, meta


def run_one(model, sm, cfg: RobustConfig, loop, kind, m_idx, seed) -> dict:
    """Draw, size, generate and diagnose one record; the facts the summary needs."""
    start = time.time()
    data, std, onsets, row = draw_record(model, sm, cfg, loop, kind, m_idx, seed)
    noise = (
        dict(zip(sm.outputs, std.tolist(), strict=True)) if cfg.noise_known else None
    )
    try:
        res = diagnose(data, model, sm.declared, loop, noise_std=noise)
    except Exception as err:  # a failed diagnosis is a record too: a miss
        return {**row, "verdict": "error", "error": repr(err), "added": [],
                "confounded": [], "forms": [], "first": False,
                "in_confounded_set": False, "named": False, "stand_in": None,
                "units": [], "flagged": [], "onset_error": [], "noise_ar": [],
                "seconds": time.time() - start}  # fmt: skip
    facts = verdict_facts(res, kind, row["name"], onsets, data)
    return {
        **row, "verdict": res.verdict, **facts,
        "forms": [c.form for c in res.members],
        "noise_ar": res.data.noise.ar[:, 0].tolist(),
        "seconds": time.time() - start,
    }  # fmt: skip


def _cells(cfg: RobustConfig, sm) -> list[tuple]:
    kinds = [k for k in sm.kinds if not cfg.kinds or k in cfg.kinds]
    # seed-major, so that a stopped run covers every cell evenly
    return [
        cell for s in range(max(cfg.seeds, cfg.clean))
        for cell in ([("none", 0, s)] if s < cfg.clean else []) + (
            [(k, i, s) for k in kinds for i in range(len(cfg.multiples))]
            if s < cfg.seeds else [])
    ]  # fmt: skip


def main(argv: list[str]) -> int:
    try:
        cfg = parse_overrides(argv, RobustConfig())
        bad = [m for m in cfg.models if m not in rs.STUDY_MODELS]
        if not 0 <= cfg.shard < cfg.shards:
            raise ValueError(f"shard: {cfg.shard} not in [0, shards={cfg.shards})")
        if bad:
            raise ValueError(f"models: unknown {bad}; valid: {list(rs.STUDY_MODELS)}")
    except ValueError as err:
        print(f"loop_robust: {err}", file=sys.stderr)
        return 2
    os.makedirs(cfg.out, exist_ok=True)
    rec_path = os.path.join(cfg.out, "records.jsonl")
    rows = []
    if os.path.exists(rec_path):
        with open(rec_path) as f:
            rows = [json.loads(line) for line in f if line.strip()]
    command = "python experiments/loop_robust.py " + " ".join(argv)
    if cfg.rerender:
        print(robust_report.write(cfg, rows, command.strip(), None))
        return 0
    enable_x64()
    enable_compilation_cache()
    loop = loop_config(cfg)
    start = time.time()
    done = {(r["model"], r["kind"], r["multiple"], r["seed"]) for r in rows}
    for name in cfg.models:
        sm = rs.STUDY_MODELS[name]
        model = load(sm.spec)
        cells = _cells(cfg, sm)
        for n, (kind, m_idx, seed) in enumerate(cells):
            mult = 0.0 if kind == "none" else cfg.multiples[m_idx]
            if (name, kind, mult, seed) in done or n % cfg.shards != cfg.shard:
                continue
            row = run_one(model, sm, cfg, loop, kind, m_idx, seed)
            rows.append(row)
            with open(rec_path, "a") as f:  # one line per record: the run resumes
                f.write(json.dumps(json_safe(row)) + "\n")
            print(f"[{name} {n + 1}/{len(cells)}] {kind:17s} {mult:4g}x seed {seed}: "
                  f"{row['verdict']:22s} added {row['added']} truth {row['name']} "
                  f"carriers {row['carriers']} flagged {row['flagged']} "
                  f"({row['rows']} rows, {row['seconds']:.1f} s)",
                  flush=True)  # fmt: skip
    minutes = (time.time() - start) / 60.0
    print(robust_report.write(cfg, rows, command.strip(), minutes))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
