"""How a diagnosis prints its numbers and its one-line summaries.

Shared by the page (:mod:`jaxcal.diagnosis.report.markdown`) and the console lines
(:mod:`jaxcal.cli.diagnose`,
experiments/loop_cmapss.py), so both use the same wording. Numbers are printed so that
they cannot mislead: a standard error that could not be estimated is "n/a", never "0"
(:func:`fmt_std`); a p-value far in the tail is "< 1e-16", never "0" or a denormal
(:func:`fmt_p`); the verdict carries its plausibility flags (:func:`verdict_line`).
"""

from __future__ import annotations

import math


def dropped_rows_line(dropped: dict) -> str:
    """``{"rows", "columns"}`` of the report as one sentence (no final stop);
    ``rows`` is ``None`` when the reader did not count them."""
    per_column = ", ".join(f"{k}: {v}" for k, v in dropped["columns"].items())
    count = "" if dropped["rows"] is None else f"{dropped['rows']} "
    return (
        f"Dropped {count}rows with NaN or Inf values before the fit "
        f"(rows per column: {per_column})"
    )


def fmt_value(v, digits=4) -> str:
    """A table cell: ``–`` for a missing value, ``digits`` significant digits for a
    float, anything else as ``str``."""
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def fmt_std(v, digits=2) -> str:
    """A standard error; never "0": one that could not be estimated is "n/a"."""
    if v is None or not math.isfinite(v) or v <= 0:
        return "n/a"
    return f"{v:.{digits}g}"


P_FLOOR = 1e-16  # below this a p-value says only "far in the tail" (model error rules)


def fmt_p(p) -> str:
    """A p-value: ``< 1e-16`` far in the tail, never 0 or a denormal."""
    if p is None or not math.isfinite(p):
        return "–"
    return f"< {P_FLOOR:.0e}" if p < P_FLOOR else f"{p:.2g}"


def effect_line(e: dict, num_units: int | None = None) -> str:
    """``name = size ± std unit`` (with the carriers when known), for one-line use."""
    form = " (per unit)" if e.get("form") == "units" else ""
    text = f"{e['name']}{form} = {e['size']:.4g} ± {fmt_std(e['std'])} {e['unit']}"
    if num_units is not None and "carriers" in e:
        text += f" (carried by {e['carriers']} of {num_units} units"
        if not e["carriers"] and e.get("min_size") is not None:
            # a per-unit effect fitted where the BIC chose it, but no unit's size
            # passed the minimum-effect test: say so, not a bare "0 of N"
            fitted = sum(u.get("size") is not None for u in e.get("units") or [])
            text += (
                f": fitted in {fitted}, none beyond its minimum size "
                f"{e['min_size']:.3g}"
            )
        text += ")"
    return text


def verdict_line(rep: dict) -> str:
    """The verdict with its plausibility flags."""
    text = f"**Verdict: {rep['verdict']}"
    flags = rep.get("flags") or []
    if flags:
        kinds = sorted({f"{f['flag']} ({f['subject']})" for f in flags})
        text += " — FLAGGED: " + "; ".join(kinds)
    return text + ".**"
