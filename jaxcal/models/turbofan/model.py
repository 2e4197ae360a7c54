"""The turbofan engines (``cmapss``, ``agtf30``) as :class:`jaxcal.Model` s.

The engine of :mod:`jaxcal.models.turbofan.physics` speaks N-CMAPSS names and units:
conditions (alt ft, Mach, TRA %, T2 degR), the ten health modifiers (0 = healthy, -0.01
= 1 % loss, bounded by the engine's envelope) and 35 outputs (the 14 measured sensors,
the 14 virtual ones and the C-MAPSS extras). Validity is the engine's own: the Newton
balance closed, the outputs are finite and the inputs lie inside the envelope (whose T2
limit is a deviation from the ISA temperature at (alt, Mach), hence ``input_check``
beside the plain box). The engine's extension inputs (bleed, power offtake, nozzle
areas, inlet recovery, T2 offset) are the model's registered effects for the diagnosis,
and its :class:`~jaxcal.model.DiagnosisHints` say what else the diagnosis should know:
the health modifiers move in steps of 1 %, the C-MAPSS FD002 noise levels are the start
noise, the fan-speed outputs follow the TRA schedule (no information), and of the
generic condition offsets only T2's is on: the registered ``t2_offset`` is an inlet
hotter than the log with the controller scheduling on the logged T2, the condition
offset on T2 is a wrong log with engine and controller both on the true inlet (the two
forms a field inlet error takes); alt, Mach and TRA offsets stay off (not part of the
validated study library, experiments/loop_study.py). Health modifiers lose in service
(``degradation_sign`` -1 for all ten).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import numpy as np

from jaxcal.model import DiagnosisHints, Model, ModelInfo, Parameter
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.constants import (
    CONDITION_NAMES,
    CONDITION_UNITS,
    HEALTH_NAMES,
    SENSOR_NAMES,
    SENSOR_UNITS,
)
from jaxcal.models.turbofan.physics.cycle import EFFECT_NAMES, NUM_UNKNOWNS
from jaxcal.models.turbofan.physics.engine import Engine, load_engine
from jaxcal.models.turbofan.physics.reference import FD002_EARLY_MEANS, FD002_EARLY_STD
from jaxcal.precision import is_x64
from jaxcal.problem import PROVISIONAL_NOISE_SHARE

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
HEALTH_SCALE = 0.01  # health modifiers are diagnosed in steps of 1 %
# Set by the fan-speed controller (TRA schedule): no information about the engine.
CONTROLLER_SET = ("Nf", "NRf", "Nf_dmd", "PCNfR_dmd")
FLEET_THETA = ("HPT_eff_mod",)  # the fleet's default declared parameter
# python -m jaxcal.prognose's defaults on C-MAPSS: the two fault modes NASA simulated,
# HPC degradation (FD001-FD004) and fan degradation (FD003 / FD004), so that a file with
# either mode needs no theta= (on FD001 the four beat the HPC pair alone: RMSE 18.5
# against 19.8; results/prognosis/), seen through the physical sensors only (the fan
# speeds are set by the controller, s11 / s12 are not physical;
# experiments/loop_cmapss.py)
PROGNOSIS_THETA = ("HPC_eff_mod", "HPC_flow_mod", "fan_eff_mod", "fan_flow_mod")
PROGNOSIS_OUTPUTS = ("T24", "T30", "T50", "P30", "Nc", "NRc", "BPR", "W31", "W32")
# the fleet's default noise without noise=: the one provisional share (1 %) of each
# output's spread (jaxcal.problem.PROVISIONAL_NOISE_SHARE)
FLEET_NOISE = (
    PROVISIONAL_NOISE_SHARE,
    f"the turbofan's default: {PROVISIONAL_NOISE_SHARE * 100:g} % of each output's "
    "spread",
)

# Outputs without a measured C-MAPSS noise level borrow the relative level of an
# output of the same kind (temperature, pressure, speed, flow).
NOISE_PROXY = {
    "T48": "T50", "T40": "T50", "P15": "P30", "P2": "P30", "P21": "P30",
    "P24": "P30", "Ps30": "P30", "P40": "P30", "P50": "P30", "P45": "P30",
    "epr": "P30", "Nf": "Nc", "NRf": "Nc", "NRc": "Nc", "Nf_dmd": "Nc",
    "PCNfR_dmd": "Nc", "Wf": "W31", "W21": "W31", "W22": "W31", "W25": "W31",
    "W48": "W31", "W50": "W31", "phi": "W31", "farB": "W31", "SmFan": "BPR",
    "SmLPC": "BPR", "SmHPC": "BPR",
}  # fmt: skip


def is_turbofan(model: Model) -> bool:
    """The model wraps the turbofan engine (``cmapss``, ``agtf30``, extended)."""
    return isinstance(getattr(model, "native", None), Engine)


def reference_noise_rel(name: str) -> float:
    """Relative noise std (std / mean) of an output, from the C-MAPSS FD002 early life.

    The median over the six operating conditions of ``FD002_EARLY_STD /
    FD002_EARLY_MEANS`` (jaxcal.models.turbofan.physics.reference); outputs C-MAPSS does
    not measure use the proxy of :data:`NOISE_PROXY`.

    Raises:
        ValueError: no reference level for ``name``.
    """
    key = NOISE_PROXY.get(name, name)
    if key not in FD002_EARLY_STD:
        raise ValueError(f"no reference noise level for sensor {name!r}")
    ratio = np.asarray(FD002_EARLY_STD[key]) / np.abs(FD002_EARLY_MEANS[key])
    return float(np.median(ratio))


def diagnosis_hints() -> DiagnosisHints:
    """What the diagnosis should know about the turbofan (module docstring)."""
    scales = {n: HEALTH_SCALE for n in HEALTH_NAMES}
    scales.update({n: EFFECT_SCALE.get(n, (1.0, "-"))[0] for n in EFFECT_NAMES})
    return DiagnosisHints(
        scales=scales,
        noise_rel={s: reference_noise_rel(s) for s in SENSOR_NAMES},
        uninformative={
            s: "set by the fan-speed controller (TRA schedule)" for s in CONTROLLER_SET
        },
        offset_conditions=("T2",),
        degradation_sign={n: -1 for n in HEALTH_NAMES},
    )


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
        x, info = evaluate_engine(engine, w, theta)
        return x, ModelInfo(valid=info.converged, native=info)

    def t2_in_envelope(w):
        dev = w[3] - isa_total_temperature(w[0], w[1])
        return (dev >= env.t2_dev_r[0]) & (dev <= env.t2_dev_r[1])

    def with_effects(w, theta, e):
        x, info = engine.evaluate(w, theta, effects=e)
        return x, ModelInfo(valid=info.converged, native=info)

    def warm(w, theta, e, z0):
        x, info = evaluate_engine_from(engine, w, theta, e, z0)
        return x, ModelInfo(valid=info.converged, native=info), info.z

    def hinted(w, theta, hint):
        x, info, hint = evaluate_engine_hinted(engine, w, theta, hint)
        return x, ModelInfo(valid=info.converged, native=info), hint

    model = Model.from_function(
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
        diagnosis=diagnosis_hints(),
        hinted_fn=hinted,
        initial_hint=engine.initial_hint,
        warm_fn=warm,
        warm_size=NUM_UNKNOWNS,
    )
    readers = dict.fromkeys((".h5", ".hdf5", ".txt"), read_file)
    return dataclasses.replace(model, file_readers=readers)


def read_file(path: str, **options):
    """An N-CMAPSS (``.h5``/``.hdf5``) or C-MAPSS (``.txt``) file -> Dataset
    (:func:`jaxcal.models.turbofan.data.datasets.read_file`: ``options``)."""
    # lazy: the readers load pandas and h5py, a model without a file need not
    from jaxcal.models.turbofan.data.datasets import read_file as read

    return read(path, **options)


def _evaluate(engine: Engine, w, theta):
    return engine.evaluate(w, theta)


# Jitted (against the style's "entry points only") because a nested jit keeps its
# traced jaxpr: the engine's large Newton graph is traced once per process and vmap
# pattern, not once per calibrator, pass and data set (tens of seconds each). The
# engine is a pytree argument, so every configuration shares the one trace.
evaluate_engine = jax.jit(_evaluate)


def _evaluate_from(engine: Engine, w, theta, effects, z0):
    return engine.evaluate_from(w, theta, effects, z0)


# The evaluation from a nearby solution (Engine.evaluate_from), jitted for the same
# reason as evaluate_engine.
evaluate_engine_from = jax.jit(_evaluate_from)


def _evaluate_hinted(engine: Engine, w, theta, hint):
    return engine.evaluate_hinted(w, theta, hint)


# The warm-started evaluation along a stream (Engine.evaluate_hinted), jitted for
# the same reason as evaluate_engine.
evaluate_engine_hinted = jax.jit(_evaluate_hinted)


def load_turbofan(name: str = "cmapss") -> Model:
    """The stored engine configuration ``name`` (``cmapss`` or ``agtf30``), cached so
    that every caller shares one model object (and so one compiled program); the
    cache is per precision, as the design constants load in the current float type."""
    return _load_turbofan(name, is_x64())


@functools.lru_cache(maxsize=8)
def _load_turbofan(name: str, x64: bool) -> Model:
    del x64  # part of the cache key only
    return turbofan_model(load_engine(name))
