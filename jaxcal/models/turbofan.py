"""The turbofan engines (``cmapss``, ``agtf30``) as :class:`jaxcal.Model` s.

The engine of :mod:`jaxcal.physics` speaks N-CMAPSS names and units: conditions
(alt ft, Mach, TRA %, T2 degR), the ten health modifiers (0 = healthy, -0.01 = 1 %
loss, bounded by the engine's envelope) and 35 outputs (the 14 measured sensors, the 14
virtual ones and the C-MAPSS extras). Validity is the engine's own: the Newton balance
closed, the outputs are finite and the inputs lie inside the envelope (whose T2 limit
is a deviation from the ISA temperature at (alt, Mach), hence ``input_check`` beside
the plain box). The engine's extension inputs (bleed, power offtake, nozzle areas,
inlet recovery, T2 offset) are the model's registered effects for the diagnosis.
"""

from __future__ import annotations

import functools

import numpy as np

from jaxcal.model import Model, ModelInfo, Parameter
from jaxcal.physics.atmosphere import isa_total_temperature
from jaxcal.physics.constants import (
    CONDITION_NAMES,
    CONDITION_UNITS,
    HEALTH_NAMES,
    SENSOR_NAMES,
    SENSOR_UNITS,
)
from jaxcal.physics.cycle import EFFECT_NAMES
from jaxcal.physics.engine import Engine, load_engine

# Natural size of one unit of each engine effect, and its unit (reporting scale).
EFFECT_SCALE = {
    "t2_offset": (1.0, "degR"),
    "customer_bleed": (0.01, "fraction of W25"),
    "power_offtake": (100.0, "hp"),
    "core_nozzle_area": (0.01, "relative"),
    "bypass_nozzle_area": (0.01, "relative"),
    "inlet_recovery": (0.001, "P2/Pt0"),
}
# Effects are bounded at this many natural units either way (a generous prior box).
EFFECT_BOUND_UNITS = 50.0


def turbofan_model(engine: Engine) -> Model:
    """The :class:`~jaxcal.model.Model` of a configured engine."""
    env = engine.envelope
    low_th, high_th = env.theta_bounds()
    parameters = {
        n: Parameter(n, 0.0, float(lo), float(hi), "-")
        for n, lo, hi in zip(HEALTH_NAMES, low_th, high_th, strict=True)
    }
    effects = {}
    for name in EFFECT_NAMES:
        scale, unit = EFFECT_SCALE.get(name, (1.0, "-"))
        bound = EFFECT_BOUND_UNITS * scale
        effects[name] = Parameter(name, 0.0, -bound, bound, unit)
    low = [env.alt_ft[0], env.mach[0], env.tra_pct[0], -np.inf]
    high = [env.alt_ft[1], env.mach[1], env.tra_pct[1], np.inf]

    def fn(w, theta):
        x, info = engine.evaluate(w, theta)
        return x, ModelInfo(valid=info.converged, native=info)

    def t2_in_envelope(w):
        dev = w[3] - isa_total_temperature(w[0], w[1])
        return (dev >= env.t2_dev_r[0]) & (dev <= env.t2_dev_r[1])

    def with_effects(w, theta, e):
        return engine.evaluate(w, theta, effects=e)[0]

    return Model.from_function(
        fn,
        conditions=dict(zip(CONDITION_NAMES, CONDITION_UNITS, strict=True)),
        parameters=parameters,
        outputs=dict(zip(SENSOR_NAMES, SENSOR_UNITS, strict=True)),
        name=engine.name,
        condition_range=(low, high),
        input_check=t2_in_envelope,
        effects=effects,
        effect_fn=with_effects,
        x64=True,
        native=engine,
    )


@functools.lru_cache(maxsize=4)
def load_turbofan(name: str = "cmapss") -> Model:
    """The stored engine configuration ``name`` (``cmapss`` or ``agtf30``), cached so
    that every caller shares one model object (and so one compiled program)."""
    return turbofan_model(load_engine(name))
