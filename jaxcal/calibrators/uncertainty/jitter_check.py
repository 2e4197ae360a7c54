"""A reported theta std is at least the estimate's own row-to-row scatter.

A filter's std is only as honest as the noise it was given. Given a noise far too
small on an output that one parameter alone explains, the filter follows that
output's noise with a std that says it knows the parameter to a fraction of what its
estimate moves from one row to the next (``results/std_coverage``).

The estimate itself shows it. For a parameter that drifts slowly against the
sampling, ``theta_t - theta_{t-1} = e_t - e_{t-1}`` plus a negligible drift, with
``e`` the estimate's error; a filter's errors are positively correlated from row to
row (its gain is at most 1), so ``var(theta_t - theta_{t-1}) <= 2 var(e)``. The
scatter ``J = robust std(theta_t - theta_{t-1}) / sqrt(2)`` (the normalised MAD, so a
step fault's one large difference does not count) is a lower bound on the error's
std. Per unit and parameter, over the unit's settled used rows: where the median
reported std is below ``J`` by more than :data:`INCONSISTENT` the std is
inconsistent with the estimate, and it is floored at ``J`` on that unit's rows;
elsewhere it is left exactly as it was (an honest std is above ``J`` on most rows,
so no number of a consistent method moves).

The check reads a unit's whole record, as the front door's noise estimate does.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from jaxcal.calibrators.front.outliers import MAD_TO_STD
from jaxcal.calibrators.front.screen import (
    SETTLE,  # the screening's: the filter locking on
)

MIN_DIFFERENCES = 3  # a unit needs this many consecutive used rows to be judged
# raised only where the scatter is this many times the median std: clearly
# inconsistent (the normalised MAD of 100 differences scatters by about 8 %)
INCONSISTENT = 1.5


def settled_rows(unit: np.ndarray, time: np.ndarray, used: np.ndarray):
    """``(order, keep)``: the rows in (unit, time) order, and ``[N]`` in that order,
    those used past their unit's first :data:`SETTLE` share (the filter locking on
    is not the estimate's behaviour)."""
    order = np.lexsort((time, unit))
    units = pd.Series(unit[order])
    position = units.groupby(units).cumcount().to_numpy()
    length = units.map(units.value_counts()).to_numpy()
    keep = np.asarray(used, bool)[order] & (position >= np.ceil(SETTLE * length))
    return order, keep


def units_shown(unit: np.ndarray, most: int = 5) -> str:
    """``"1, 2, 3"`` of the distinct ``unit`` values, ``"... and N more"`` past
    ``most``."""
    units = np.unique(unit)
    more = f" and {len(units) - most} more" if len(units) > most else ""
    return ", ".join(str(u) for u in units[:most]) + more


def jitter_floor(
    unit: np.ndarray, time: np.ndarray, theta: np.ndarray, std: np.ndarray,
    valid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The std floored where it is below the estimate's scatter (module doc).

    Args:
        unit, time: ``[N]`` each row's unit and time (any row order).
        theta, std: ``[N, P]`` the estimate and its reported std.
        valid: ``[N]`` bool, the rows the method used.

    Returns:
        ``(std, factor)``: ``[N, P]`` the checked std, and ``[N, P]`` the factor by
        which the unit's median std was raised (1 where the std was consistent).
    """
    order, keep = settled_rows(unit, time, valid)
    kept_unit = unit[order][keep]
    steps = np.diff(theta[order][keep], axis=0)
    same = kept_unit[1:] == kept_unit[:-1]
    key = kept_unit[1:][same]
    diffs = pd.DataFrame(steps[same])
    deviation = (diffs - diffs.groupby(key).transform("median")).abs()
    scatter = deviation.groupby(key).median() * MAD_TO_STD / np.sqrt(2)
    scatter = scatter[diffs.groupby(key).size() >= MIN_DIFFERENCES]
    typical = pd.DataFrame(std[order][keep]).groupby(kept_unit).median()
    typical = typical.reindex(scatter.index).to_numpy()
    raised = INCONSISTENT * typical < scatter.to_numpy()  # [units judged, P]
    floor = scatter.where(raised, 0.0)
    checked = np.maximum(std, floor.reindex(unit).fillna(0.0).to_numpy())
    ratio = pd.DataFrame(np.where(raised, scatter.to_numpy() / typical, 1.0))
    factor = ratio.set_axis(scatter.index).reindex(unit).fillna(1.0).to_numpy()
    return checked, factor


def jitter_note(factor: np.ndarray, unit: np.ndarray, names) -> list[str]:
    """The console line when :func:`jitter_floor` raised a std (else nothing)."""
    raised = factor > 1
    if not raised.any():
        return []
    parts = []
    for p, name in enumerate(names):
        if raised[:, p].any():
            shown = units_shown(unit[raised[:, p]])
            parts.append(f"{name} (units {shown}, x{np.max(factor[:, p]):.3g})")
    return [
        "theta_std raised to the estimate's own row-to-row scatter on "
        + "; ".join(parts)
        + ": the reported std was below what the estimate moves from row to row "
        "(as when the noise is far too small for an output one parameter explains "
        "alone, or when the model misfits and the estimate chases the misfit)"
    ]
