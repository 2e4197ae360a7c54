"""The robust study's records diagnosed before issue 24 and now, on the same records.

Three steps, each a command::

    python experiments/loop_before.py write [models=turbofan,heat_exchanger,thermal]
        [seeds=4] [clean=8] [kinds=...] [records=data/loop_before]
    PYTHONPATH=/tmp/before python experiments/loop_before.py run label=before \\
        [records=data/loop_before] [out=results/loop/robust/levers/before_after]
    python experiments/loop_before.py run label=after [records=...] [out=...]
        [models=...] [shard=0/2]  (a part of the records: processes side by side)
    python experiments/loop_before.py compare [out=...]

``write`` draws exactly the records of the robust study (``loop_robust.py``: the
same tags, the same draws, sizes at multiples of each record's detectability size,
``loop_robust.draw_record``) for the first ``seeds`` seeds of every (model, kind,
multiple) and the first ``clean`` clean ones (``kinds=none,sensor_bias`` keeps
those kinds only; ``none`` is the clean records), and stores each as Parquet (the
conditions, the outputs, ``unit``, ``time``) with one ``truth.json`` listing file,
model, kind, multiple, seed, name, target, size, s1, carriers, onsets and units. The
records are data (``data/``, not committed). Resumable: a stored record is kept.

``run`` diagnoses every stored record with whatever ``jaxcal`` is on the path, with
its default settings (noise estimated), and appends one row per record to
``<out>/<label>.jsonl`` in the robust study's row shape (``robust_report`` summarises
them; resumable). The diagnosis before issue 24 is a checkout of 74da562::

    git worktree add /tmp/before 74da562
    PYTHONPATH=/tmp/before python experiments/loop_before.py run label=before
    git worktree remove --force /tmp/before

That checkout has no thermal model: the thermal model is then defined here from its
equations (:func:`_thermal`, the same network as ``jaxcal/models/thermal.py``). This
file imports nothing from ``jaxcal`` at module level, so that it runs on either.

``compare`` writes ``<out>/README.md`` (per model: false alarms, identification per
kind at each multiple, unit hit rate and onset error, before against after) and
``<out>/summary.json`` (``{"before": ..., "after": ...}``, each in the shape of
``robust_report.summarize``).

The reading of a diagnosis against the truth (named, stand-in, flagged carriers,
onset error) is :func:`verdict_facts`, which ``loop_robust.py`` uses too.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
MODELS = ("turbofan", "heat_exchanger", "thermal")
RECORDS = "data/loop_before"  # generated records (git-ignored)
OUT = "results/loop/robust/levers/before_after"
LABELS = ("before", "after")
OPTIONS = {
    "write": {"models": ",".join(MODELS), "seeds": "4", "clean": "8", "kinds": "",
              "records": RECORDS},
    "run": {"label": "", "records": RECORDS, "out": OUT, "models": "", "shard": "0/1"},
    "compare": {"out": OUT},
}  # fmt: skip


# ------------------------------------------------ the reading of a diagnosis


def verdict_facts(res, kind: str, name: str, onsets: dict, data) -> dict:
    """What a diagnosis ``res`` of a record says about its truth.

    ``named``: the diagnosis adds exactly the true effect ``name`` (besides a
    discrepancy), or, where the data cannot tell two effects apart, its verdict is
    ``confounded`` with a set that holds the truth and the one effect it added,
    which then stands in for the truth (``stand_in``) in the per-unit verdict;
    ``first``: exactly the truth added. ``flagged``: the units whose per-unit
    verdict on the stand-in says they carry it (none when the truth is not named,
    or when the result has no per-unit verdict); ``onset_error``: over the flagged
    units with a true onset (a step) and a finite estimated one, ``|onset - truth|``
    as a share of the unit's record length. ``onsets``: true onset cycle per carrier
    (int keys); ``data``: the record (``time``, ``unit``). Attributes a diagnosis of
    an older checkout lacks are read with ``getattr``.
    """
    added = [a for a in res.added if a != "discrepancy"]
    confounded = list(getattr(res, "confounded", None) or [])
    named = bool(kind != "none" and (added == [name] or (
        res.verdict.startswith("confounded") and name in confounded
        and len(added) == 1 and added[0] in confounded)))  # fmt: skip
    stand_in = added[0] if named else None
    ids = res.data.unit_ids.tolist()
    flagged, onset_err = [], []
    for eff in getattr(res, "unit_effects", None) or ():
        if eff.name != stand_in:
            continue
        flagged = [int(u) for u, c in zip(ids, eff.carries, strict=True) if c]
        onset = getattr(eff, "onset", None)
        if onset is None:
            continue
        for u in flagged:
            if u in onsets and np.isfinite(onset[ids.index(u)]):
                length = float(np.ptp(data.time[data.unit == u]) + 1)
                onset_err.append(abs(onset[ids.index(u)] - onsets[u]) / length)
    return {
        "added": added, "confounded": confounded,
        "first": bool(kind != "none" and added == [name]),
        "in_confounded_set": name in confounded, "named": named,
        "stand_in": stand_in, "units": list(ids), "flagged": flagged,
        "onset_error": onset_err,
    }  # fmt: skip


# ------------------------------------------------------------------- helpers


def _plain(value):
    """JSON-ready: numpy scalars and arrays to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _write_json(path: str, payload) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(_plain(payload), f, indent=1)
        f.write("\n")
    os.replace(tmp, path)


def _read_jsonl(path: str) -> list[dict]:
    """Rows of a resumable run; a record run twice keeps its last row."""
    if not os.path.exists(path):
        return []
    rows = {}
    with open(path) as f:
        for line in f:
            if line.strip():
                r = json.loads(line)
                rows[_key(r)] = r
    return list(rows.values())


def _key(r: dict) -> tuple:
    return (r["model"], r["kind"], float(r["multiple"]), int(r["seed"]))


def _enable_x64() -> None:
    try:
        from jaxcal.precision import enable_x64
    except ImportError:  # pragma: no cover - any checkout has it today
        import jax

        jax.config.update("jax_enable_x64", True)
        return
    try:
        from jaxcal.cache import enable_compilation_cache
    except ImportError:  # a checkout before issue 26
        from jaxcal.precision import enable_compilation_cache
    enable_x64()
    enable_compilation_cache()


def _code() -> dict:
    """Which jaxcal runs: its folder and, in a git checkout, its commit."""
    import jaxcal

    where = os.path.dirname(os.path.dirname(os.path.abspath(jaxcal.__file__)))
    try:
        commit = subprocess.run(
            ["git", "-C", where, "rev-parse", "--short", "HEAD"], check=True,
            capture_output=True, text=True,
        ).stdout.strip()  # fmt: skip
        dirty = subprocess.run(
            ["git", "-C", where, "status", "--porcelain", "--", "jaxcal"],
            check=True, capture_output=True, text=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        commit, dirty = None, ""
    return {"path": where, "commit": commit, "jaxcal_modified": bool(dirty)}


# --------------------------------------------------------------------- write


def write(opts: dict) -> int:
    """Draw and store the records (module docstring)."""
    _enable_x64()
    sys.path.insert(0, HERE)
    import loop_robust as lr
    import robust_scenario as rs

    from jaxcal.models import load

    models = [m for m in opts["models"].split(",") if m]
    bad = [m for m in models if m not in rs.STUDY_MODELS]
    if bad:
        print(f"loop_before: models: unknown {bad}; valid: {list(rs.STUDY_MODELS)}",
              file=sys.stderr)  # fmt: skip
        return 2
    kinds = tuple(k for k in opts["kinds"].split(",") if k)
    known = {"none"} | {k for m in models for k in rs.STUDY_MODELS[m].kinds}
    if set(kinds) - known:
        print(f"loop_before: kinds: unknown {sorted(set(kinds) - known)}; valid for "
              f"these models: {sorted(known)}", file=sys.stderr)  # fmt: skip
        return 2
    cfg = lr.RobustConfig(models=tuple(models), seeds=int(opts["seeds"]),
                          clean=int(opts["clean"]))  # fmt: skip
    loop = lr.loop_config(cfg)
    records = opts["records"]
    os.makedirs(records, exist_ok=True)
    truth_path = os.path.join(records, "truth.json")
    truth = []
    if os.path.exists(truth_path):
        with open(truth_path) as f:
            truth = json.load(f)
    done = {_key(t) for t in truth
            if os.path.exists(os.path.join(records, t["file"]))}  # fmt: skip
    truth = [t for t in truth if _key(t) in done]
    for name in models:
        sm = rs.STUDY_MODELS[name]
        model = load(sm.spec)
        cells = [c for c in lr._cells(cfg, sm) if not kinds or c[0] in kinds]
        for n, (kind, m_idx, seed) in enumerate(cells):
            mult = 0.0 if kind == "none" else cfg.multiples[m_idx]
            if (name, kind, mult, seed) in done:
                continue
            start = time.time()
            data, _, onsets, meta = lr.draw_record(model, sm, cfg, loop, kind, m_idx,
                                                   seed)  # fmt: skip
            frame = {c: data.w[:, j] for j, c in enumerate(data.condition_names)}
            frame |= {s: data.x[:, j] for j, s in enumerate(data.output_names)}
            frame |= {"unit": data.unit, "time": data.time}
            import pandas as pd

            file = f"{name}_{kind}_{mult:g}x_{seed}.parquet"
            pd.DataFrame(frame).to_parquet(os.path.join(records, file), index=False)
            truth.append({
                "file": file, "model": name, "spec": sm.spec,
                "declared": list(sm.declared), "kind": kind, "multiple": mult,
                "seed": seed, "name": meta["name"], "target": meta["target"],
                "size": meta["size"], "s1": meta["s1"],
                "carriers": meta["carriers"], "onsets": meta["onsets"],
                "units": sorted({int(u) for u in data.unit}), "rows": meta["rows"],
                "conditions": list(data.condition_names),
                "outputs": list(data.output_names), "setting": meta["setting"],
            })  # fmt: skip
            _write_json(truth_path, truth)  # after every record: resumable
            print(f"[{name} {n + 1}/{len(cells)}] {kind:17s} {mult:4g}x seed {seed}: "
                  f"{meta['name'] or '-'} size {meta['size']:.4g} carriers "
                  f"{meta['carriers']} ({meta['rows']} rows, "
                  f"{time.time() - start:.1f} s) -> {file}", flush=True)  # fmt: skip
    print(f"{len(truth)} records in {truth_path}")
    return 0


# ----------------------------------------------------------------------- run


def _thermal():
    """The two-mass heated body of ``jaxcal/models/thermal.py``, from its equations,
    for a checkout that does not have it (the one of before issue 24)."""
    import jax.numpy as jnp

    from jaxcal.model import Model

    dt = 60.0  # s per sample

    def steady(w, th):
        shell = w[1] + w[0] * th[0]
        return jnp.stack([shell + w[0] * th[1], shell])

    def expm2(a):  # exp of a 2x2 matrix with real eigenvalues (Cayley-Hamilton)
        m = 0.5 * (a[0, 0] + a[1, 1])
        det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
        d = jnp.sqrt(jnp.maximum(m * m - det, 1e-300))
        eye = jnp.eye(2, dtype=a.dtype)
        return jnp.exp(m) * (jnp.cosh(d) * eye + (jnp.sinh(d) / d) * (a - m * eye))

    def step(z, w, th):
        r_sa, r_cs, c_core, c_shell = th[0], th[1], th[2], th[3]
        a = jnp.array(
            [
                [-1 / (r_cs * c_core), 1 / (r_cs * c_core)],
                [1 / (r_cs * c_shell), -(1 / r_cs + 1 / r_sa) / c_shell],
            ]
        )
        z_ss = steady(w, th)
        z2 = z_ss + expm2(a * dt) @ (z - z_ss)
        return z2, jnp.stack([z2[0], z2[1], (z2[1] - w[1]) / r_sa])

    return Model.from_step(
        step, init_state=steady, states={"core": "K", "shell": "K"},
        conditions={"power": "W", "ambient": "K"},
        parameters={"R_sa": (0.02, 0.01, 0.03, "K/W"),
                    "R_cs": (0.01, 0.005, 0.02, "K/W"),
                    "C_core": (2.0e5, 1.0e5, 4.0e5, "J/K"),
                    "C_shell": (5.0e4, 2.5e4, 1.0e5, "J/K")},
        outputs={"T_core": "K", "T_shell": "K", "q_loss": "W"}, name="thermal",
        condition_range=([0.0, 250.0], [3000.0, 320.0]),
    )  # fmt: skip


def _model(spec: str):
    """``(model, source)``: the registered model, or the thermal model from its
    equations where this checkout has no such name."""
    from jaxcal.models import load

    try:
        return load(spec), "jaxcal.models"
    except ValueError:
        if spec != "thermal":
            raise
        return _thermal(), "equations (loop_before._thermal)"


def run(opts: dict) -> int:
    """Diagnose every stored record with the jaxcal on the path (docstring)."""
    label = opts["label"]
    if label not in LABELS:
        print(f"loop_before: run needs label=before|after, got {label!r}",
              file=sys.stderr)  # fmt: skip
        return 2
    _enable_x64()
    import pandas as pd

    from jaxcal.data.dataset import Dataset
    from jaxcal.diagnosis.pipeline import diagnose

    code = _code()
    print(f"{label}: jaxcal from {code['path']} (commit {code['commit']}"
          f"{', jaxcal/ modified' if code['jaxcal_modified'] else ''})")  # fmt: skip
    with open(os.path.join(opts["records"], "truth.json")) as f:
        truth = json.load(f)
    if opts["models"]:  # a part of the records (processes side by side, one file)
        truth = [t for t in truth if t["model"] in opts["models"].split(",")]
    shard, shards = (int(v) for v in opts["shard"].split("/"))
    truth = truth[shard::shards]  # shard=i/n: every n-th record from the i-th
    os.makedirs(opts["out"], exist_ok=True)
    path = os.path.join(opts["out"], f"{label}.jsonl")
    done = {_key(r) for r in _read_jsonl(path)}
    models = {}
    for n, t in enumerate(truth):
        if _key(t) in done:
            continue
        if t["spec"] not in models:
            models[t["spec"]] = _model(t["spec"])
        model, source = models[t["spec"]]
        frame = pd.read_parquet(os.path.join(opts["records"], t["file"]))
        data = Dataset(
            w=frame[t["conditions"]].to_numpy(np.float64),
            x=frame[t["outputs"]].to_numpy(np.float64),
            condition_names=tuple(t["conditions"]),
            output_names=tuple(t["outputs"]),
            unit=frame["unit"].to_numpy(np.int64),
            time=frame["time"].to_numpy(np.float64), source=t["file"],
        )  # fmt: skip
        onsets = {int(k): float(v) for k, v in t["onsets"].items()}
        row = {k: t[k] for k in ("model", "kind", "multiple", "seed", "target", "name",
                                 "size", "s1", "carriers", "rows")}  # fmt: skip
        row |= {"onsets": t["onsets"], "label": label, "code": code,
                "model_source": source}  # fmt: skip
        start = time.time()
        try:
            res = diagnose(data, model, tuple(t["declared"]))
        except Exception as err:  # a failed diagnosis is a record too: a miss
            res, facts = None, {
                "verdict": "error", "error": repr(err), "added": [],
                "confounded": [], "first": False, "in_confounded_set": False,
                "named": False, "stand_in": None, "units": [], "flagged": [],
                "onset_error": [],
            }  # fmt: skip
        else:
            facts = {
                "verdict": res.verdict,
                **verdict_facts(res, t["kind"], t["name"], onsets, data),
            }
        members = getattr(res, "members", None) or ()
        noise = getattr(getattr(res, "data", None), "noise", None)
        row |= facts | {
            # the per-unit verdict and its onsets, where the result has them
            "per_unit": res is not None and hasattr(res, "unit_effects"),
            "onset_reported": res is not None and all(
                hasattr(e, "onset") for e in getattr(res, "unit_effects", ()) or ()),
            "forms": [getattr(c, "form", None) for c in members],
            "noise_ar": [] if noise is None else noise.ar[:, 0].tolist(),
            "seconds": time.time() - start,
        }  # fmt: skip
        with open(path, "a") as f:  # one line per record: the run resumes
            f.write(json.dumps(_plain(row)) + "\n")
        print(f"[{label} {n + 1}/{len(truth)}] {t['model']:14s} {t['kind']:17s} "
              f"{t['multiple']:4g}x seed {t['seed']}: {row['verdict']:22s} added "
              f"{row['added']} truth {t['name'] or '-'} carriers {t['carriers']} "
              f"flagged {row['flagged']} ({row['seconds']:.1f} s)",
              flush=True)  # fmt: skip
    return 0


# ------------------------------------------------------------------- compare


def _fmt(v) -> str:
    return "–" if v is None else f"{v:.2f}"


def _pair(before, after) -> str:
    return f"{_fmt(before)} → {_fmt(after)}"


def _ident_table(sb: dict, sa: dict, cb: dict, ca: dict, mults) -> list[str]:
    keys = [f"{m:g}x" for m in mults]
    lines = [
        "| kind | " + " | ".join(f"named {k}" for k in keys)
        + " | " + " | ".join(f"strict {k}" for k in keys) + " | n per cell |",
        "|---|" + "---|" * (2 * len(keys) + 1),
    ]  # fmt: skip
    if not sa["identification"] and not sb["identification"]:
        return ["No effect records."]
    for kind in sorted(set(sa["identification"]) | set(sb["identification"])):
        rb = sb["identification"].get(kind, {})
        ra = sa["identification"].get(kind, {})
        tb = cb["identification_strict"].get(kind, {})
        ta = ca["identification_strict"].get(kind, {})
        ns = sorted(set(ca["identification"].get(kind, {}).values())
                    | set(cb["identification"].get(kind, {}).values()))  # fmt: skip
        lines.append(
            f"| {kind} | "
            + " | ".join(_pair(rb.get(k), ra.get(k)) for k in keys)
            + " | " + " | ".join(_pair(tb.get(k), ta.get(k)) for k in keys)
            + f" | {'/'.join(str(n) for n in ns)} |"
        )  # fmt: skip
    return lines


def _target_of(name: str) -> str:
    """``sensor_bias[T30]`` -> ``T30``; a registered effect is its own target."""
    return name.split("[", 1)[1].rstrip("]") if "[" in name else name


def _other_form(rows: list[dict]) -> float | None:
    """Share of effect records not named where an added effect acts on the true
    target in another form (e.g. a step added as a smooth parameter change)."""
    eff = [r for r in rows if r["kind"] != "none"]
    hits = [not r["named"] and any(_target_of(a) == r["target"] and a != r["name"]
                                   for a in r["added"]) for r in eff]  # fmt: skip
    return float(np.mean(hits)) if hits else None


def _facts_lines(sb, sa, cb, ca, before, after) -> list[str]:
    n_eff = sum(r["kind"] != "none" for r in after)
    return [
        "| | before | after | n (before / after) |",
        "|---|---|---|---|",
        f"| false alarms | {_fmt(sb['false_alarm_rate'])} | "
        f"{_fmt(sa['false_alarm_rate'])} | {cb['clean']} / {ca['clean']} |",
        f"| unit hit rate (>= 5x) | {_fmt(sb['unit_hit_rate'])} | "
        f"{_fmt(sa['unit_hit_rate'])} | {cb['carriers_5x']} / {ca['carriers_5x']} |",
        f"| non-carriers flagged (truth named) | {_fmt(cb['unit_false_flag_rate'])} "
        f"| {_fmt(ca['unit_false_flag_rate'])} | {cb['non_carriers']} / "
        f"{ca['non_carriers']} |",
        f"| onset error (median, step kinds) | {_fmt(sb['onset_error'])} | "
        f"{_fmt(sa['onset_error'])} | {cb['onsets']} / {ca['onsets']} |",
        f"| true target in another form only (not named) | "
        f"{_fmt(_other_form(before))} | {_fmt(_other_form(after))} | {n_eff} |",
        f"| diagnoses that raised an error | {cb['errors']} | {ca['errors']} | |",
    ]


def _changes(before: list[dict], after: list[dict]) -> tuple[int, int, int]:
    """Effect records named now but not before, before but not now, and both."""
    b = {_key(r): r for r in before if r["kind"] != "none"}
    pairs = [(b[_key(r)], r) for r in after if _key(r) in b]
    return (sum(a["named"] and not o["named"] for o, a in pairs),
            sum(o["named"] and not a["named"] for o, a in pairs),
            sum(o["named"] and a["named"] for o, a in pairs))  # fmt: skip


def compare(opts: dict) -> int:
    """Write ``<out>/README.md`` and ``<out>/summary.json`` (module docstring)."""
    sys.path.insert(0, HERE)
    import robust_report

    out = opts["out"]
    runs = {}
    for label in LABELS:
        path = os.path.join(out, f"{label}.jsonl")
        if not os.path.exists(path):
            print(f"loop_before: {path} missing: run label={label} first",
                  file=sys.stderr)  # fmt: skip
            return 2
        runs[label] = _read_jsonl(path)
    common = {_key(r) for r in runs["before"]} & {_key(r) for r in runs["after"]}
    rows = {k: [r for r in v if _key(r) in common] for k, v in runs.items()}
    left = {k: len(v) - len(rows[k]) for k, v in runs.items()}
    mults = sorted({float(r["multiple"]) for r in rows["after"] if r["kind"] != "none"})
    summ = {k: robust_report.summarize(v, mults) for k, v in rows.items()}
    _write_json(os.path.join(out, "summary.json"),
                {k: s for k, (s, _) in summ.items()})  # fmt: skip
    (sb, cb), (sa, ca) = summ["before"], summ["after"]
    code = {k: (v[0]["code"] if v else {}) for k, v in rows.items()}
    sources = sorted({f"{r['model']}: {r['model_source']}" for r in rows["before"]
                      if r["model_source"] != "jaxcal.models"})  # fmt: skip
    ran = [r for r in rows["before"] if r["verdict"] != "error"]
    no_unit = sum(not r["per_unit"] for r in ran)
    no_onset = sum(r["per_unit"] and not r["onset_reported"] for r in ran)
    lines = [
        "# The robust study's records: the diagnosis before issue 24 against now",
        "",
        f"The same {len(common)} records (drawn as `experiments/loop_robust.py` draws "
        "them, sizes at multiples of each record's own detectability size; stored "
        "as Parquet by `experiments/loop_before.py write`) diagnosed by the checkout "
        f"before issue 24 (commit {code['before'].get('commit')}) and by this one "
        f"(commit {code['after'].get('commit')}"
        f"{', jaxcal/ modified' if code['after'].get('jaxcal_modified') else ''}), "
        "each with its default settings, noise level (and, now, colour) estimated. "
        "Commands:",
        "",
        "```",
        "python experiments/loop_before.py write [models=...] [seeds=4] [clean=8]",
        "git worktree add /tmp/before 74da562",
        "PYTHONPATH=/tmp/before python experiments/loop_before.py run label=before",
        "python experiments/loop_before.py run label=after",
        "python experiments/loop_before.py compare",
        "```",
        "",
        "Cells are before → after. *Named*: the diagnosis adds the true effect, or "
        "reports it in a confounded set with the one effect it adds; *strict*: it "
        "adds exactly the truth. The unit hit rate counts carriers flagged by the "
        "per-unit verdict on the named effect (its stand-in), sizes >= 5x.",
        "",
        "What the diagnosis before issue 24 could not do, by construction: its "
        "library had no step kinds (`sensor_step`, `parameter_step` cannot be named, "
        "so their identification, unit hits and onset error are 0 or empty before); "
        "it had no noise colour (white noise) and no per-unit forms; a model with "
        "memory was diagnosed on its one-step (UKF-filtered) residual. "
        + (f"Models defined here from their equations for that checkout: "
           f"{'; '.join(sources)}. " if sources else "")
        + (f"{no_unit} of its results had no per-unit verdict (`unit_effects`): "
           "no unit is counted as flagged there. " if no_unit else "")
        + (f"{no_onset} of its per-unit verdicts had no onset: no onset error "
           "there. " if no_onset else "")
        + "On the thermal model the before column is the one-step diagnosis, so "
        "those rows show the output-error form together with the other levers. "
        + "Rows in `before.jsonl` / `after.jsonl`.",
        "",
    ]  # fmt: skip
    if any(left.values()):
        lines += [f"Left out (diagnosed by one side only): {left}.", ""]
    new, lost, both = _changes(rows["before"], rows["after"])
    lines += [
        f"**All models.** Effect records named now and not before: {new}; named "
        f"before and not now: {lost}; named by both: {both}.",
        "",
        *_facts_lines(sb, sa, cb, ca, rows["before"], rows["after"]),
        "",
        *_ident_table(sb, sa, cb, ca, mults),
        "",
    ]
    for model in sorted(sa["per_model"]):
        pb, pa = sb["per_model"].get(model), sa["per_model"][model]
        qb, qa = cb["per_model"].get(model), ca["per_model"][model]
        mine = {k: [r for r in v if r["model"] == model] for k, v in rows.items()}
        new, lost, both = _changes(mine["before"], mine["after"])
        lines += [
            f"## {model}",
            "",
            f"Named now and not before: {new}; before and not now: {lost}; both: "
            f"{both}.",
            "",
            *_facts_lines(pb, pa, qb, qa, mine["before"], mine["after"]),
            "",
            *_ident_table(pb, pa, qb, qa, mults),
            "",
        ]
    text = "\n".join(lines) + "\n"
    tmp = os.path.join(out, "README.md.tmp")
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, os.path.join(out, "README.md"))
    print(text)
    return 0


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in OPTIONS:
        print(f"usage: loop_before.py {{{'|'.join(OPTIONS)}}} [key=value ...]",
              file=sys.stderr)  # fmt: skip
        return 2
    mode, opts = argv[0], dict(OPTIONS[argv[0]])
    for arg in argv[1:]:
        key, eq, value = arg.partition("=")
        if not eq or key not in opts:
            print(f"loop_before {mode}: unknown option {arg!r}; valid: "
                  f"{', '.join(opts)}", file=sys.stderr)  # fmt: skip
            return 2
        opts[key] = value
    return {"write": write, "run": run, "compare": compare}[mode](opts)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
