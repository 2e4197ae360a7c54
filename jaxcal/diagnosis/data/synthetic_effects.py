"""How one effect is switched on in the rows of a synthetic data set.

:func:`apply_effect` puts an effect of the library (:mod:`jaxcal.diagnosis.kinds.table`)
into the extended
model's inputs, sized in physical units; :func:`add_bump` adds the effect outside the
library, the discrepancy bump ``A sigma exp(-((w_c - c0) / width)^2)`` on one output
(:mod:`jaxcal.diagnosis.data.synthetic`).
"""

from __future__ import annotations

import numpy as np

from jaxcal.diagnosis.kinds.table import KINDS, natural_scale
from jaxcal.model import Model


def kind_of(model: Model, label: str):
    """The :data:`~jaxcal.diagnosis.kinds.table.KINDS` entry of a study label."""
    if label in KINDS:
        return KINDS[label]
    if label in [e.name for e in model.effects]:
        return KINDS["effect"]
    raise ValueError(f"no effect kind {label!r}")


def apply_effect(model, kind, tgt, size, parameter_physical, inputs, on, step_on, tau,
                 health, std, level, sensors, w):  # fmt: skip
    """Switch the effect on in ``inputs`` (in place); ``(size, unit)`` physical.

    Args:
        kind, tgt, size: the effect, its target and its size in the units of
            ``SyntheticConfig.sizes`` (``parameter_physical`` as there).
        inputs: the extended model's row inputs
        (:func:`jaxcal.diagnosis.kinds.signatures.zero_inputs`).
        on: ``[N]`` bool, the carriers' rows; step_on: ``[N]`` after a step's onset;
            tau: ``[N]`` drift time; health: ``[N]`` health index.
        std, level: ``[S]`` noise std and mean ``|x|`` of the outputs ``sensors``.
        w: ``[N, W]`` conditions.
    """
    if kind in ("none", "discrepancy"):
        return size, "-"
    spec = kind_of(model, kind)
    channel = spec.channel
    profile = {
        "constant": np.ones_like(tau),
        "drift": tau,
        "step": step_on.astype(float),
        "spline": 1.0 - health,
    }[spec.profile]
    profile = profile * on
    if channel == "parameter":
        j = model.parameter_names.index(tgt)
        step = 1.0 if parameter_physical and kind == "parameter" else (
            natural_scale(model, tgt)
        )  # fmt: skip
        size = size * step
        inputs.theta[:, j] += size * profile
        return size, model.unit_of(tgt)
    if channel == "effect":
        e = [x.name for x in model.effects].index(tgt)
        inputs.effects[:, e] += size * profile
        return size, model.effects[e].unit
    if channel == "condition":
        c = model.condition_names.index(tgt)
        size = size * 0.01 * float(np.std(w[:, c]) or 1.0)
        inputs.w_offset[:, c] += size * profile
        return size, model.conditions[c].unit
    s = list(sensors).index(tgt)
    idx = model.output_index([tgt])[0]
    relative = channel == "multiplicative"
    size = size * (std[s] / level[s] if relative else std[s])
    field = inputs.multiplicative if relative else inputs.additive
    field[:, idx] += size * profile
    return size, spec.physical_unit(model, tgt)


def add_bump(rng, model: Model, bump, x_s: np.ndarray, amplitude: float, w, on):
    """Add the discrepancy bump to one output's column ``x_s`` (in place).

    Args:
        rng: numpy generator (draws the centre c0).
        bump: ``SyntheticConfig.bump`` or ``None`` (:func:`_default_bump`).
        x_s: ``[N]`` the output's values; amplitude: ``A sigma`` in its units.
        w: ``[N, W]`` conditions; on: ``[N]`` bool, the carriers' rows.

    Returns:
        ``(the bump's condition, amplitude)``.
    """
    bump_on, (c_lo, c_hi), width = bump or _default_bump(model, w)
    c = model.condition_names.index(bump_on)
    c0 = rng.uniform(c_lo, c_hi)
    x_s += on * amplitude * np.exp(-(((w[:, c] - c0) / width) ** 2))
    return bump_on, amplitude


def _default_bump(model: Model, w: np.ndarray):
    """The first condition that varies, the centre between its 45th and 65th
    percentile, the width 20 % of its spread."""
    spread = w.std(0)
    c = int(np.argmax(spread > 0))
    lo, hi = np.percentile(w[:, c], [45.0, 65.0])
    return model.condition_names[c], (float(lo), float(hi)), 0.2 * float(spread[c])
