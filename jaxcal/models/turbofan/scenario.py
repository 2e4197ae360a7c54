"""N-CMAPSS-like fleets of the turbofan for synthetic diagnosis studies.

A scenario is the clean part of a synthetic data set
(:mod:`jaxcal.diagnosis.data.synthetic`
adds one effect and the noise): each unit flies a run-to-failure life
(:func:`jaxcal.models.turbofan.data.degradation.sample_unit_degradation`, the declared
modifiers degrade with the unit's health index) and every cycle is a climb / cruise /
descent flight (:func:`jaxcal.models.turbofan.data.flights.sample_flight`) from which
``rows_per_cycle`` random recorded samples are kept, so that a data set holds a
realistic number of cycles at a size a test can afford.

:data:`EFFECT_SIZES` are the turbofan's study sizes in physical units (the undeclared
health modifier's end-of-life value, the engine effects in their own units, the output
layers in noise std) and :data:`DISCREPANCY_BUMP` the bump outside the library (in
Mach); :data:`STUDY_OUTPUTS` the measured sensors but the controller-set fan speed.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.models.turbofan.data.degradation import (
    DegradationConfig,
    sample_unit_degradation,
)
from jaxcal.models.turbofan.data.flights import FlightConfig, sample_flight
from jaxcal.models.turbofan.physics.constants import MEASURED_SENSOR_NAMES

STUDY_OUTPUTS = tuple(s for s in MEASURED_SENSOR_NAMES if s != "Nf")
# kind -> ((low, high) magnitude, sign): +1 positive, -1 negative, 0 random sign.
EFFECT_SIZES: dict[str, tuple[tuple[float, float], int]] = {
    "parameter": ((0.005, 0.02), -1),  # end-of-life value of the modifier
    "t2_offset": ((1.0, 3.0), 0),  # degR
    "customer_bleed": ((0.005, 0.02), 1),  # fraction of W25
    "power_offtake": ((150.0, 500.0), 1),  # hp
    "core_nozzle_area": ((0.01, 0.03), 0),  # relative
    "bypass_nozzle_area": ((0.01, 0.03), 0),  # relative
    "inlet_recovery": ((0.003, 0.01), -1),  # P2/Pt0
    "sensor_bias": ((2.0, 5.0), 0),  # noise std
    "sensor_gain": ((2.0, 5.0), 0),  # noise std / mean level
    "sensor_drift": ((3.0, 6.0), 0),  # noise std per 100 cycles
    "sensor_gain_drift": ((3.0, 6.0), 0),  # noise std / mean level per 100 cycles
    "condition_offset": ((2.0, 6.0), 1),  # % of T2's std (T2 is the one offset)
    "discrepancy": ((3.0, 6.0), 0),  # noise std (bump height)
}
DISCREPANCY_BUMP = ("Mach", (0.45, 0.65), 0.12)  # condition, centre range, width


@dataclasses.dataclass(frozen=True)
class ScenarioConfig:
    """Static settings of :func:`make_scenario`."""

    num_units: int = 3
    rows_per_cycle: int = 2  # recorded samples kept per flight
    cycle_stride: int = 1  # keep every k-th cycle of each life
    declared: tuple[str, ...] = ("HPT_eff_mod",)  # modifiers that degrade
    flight: FlightConfig = FlightConfig(dt_s=60.0)  # 1-min samples are plenty here

    def __post_init__(self):
        if self.num_units < 1 or self.rows_per_cycle < 1 or self.cycle_stride < 1:
            raise ValueError(
                "ScenarioConfig: num_units, rows_per_cycle, cycle_stride >= 1"
            )


class FleetRows(NamedTuple):
    """Clean rows (the ``Scenario`` of :mod:`jaxcal.diagnosis.data.synthetic`)."""

    w: np.ndarray  # [N, 4]
    theta: np.ndarray  # [N, 10]
    unit: np.ndarray  # [N] unit id from 1
    cycle: np.ndarray  # [N] from 1
    health: np.ndarray  # [N] health index


@functools.partial(jax.jit, static_argnums=(2, 3))
def _sample_fleet(key_deg, key_flight, deg_cfg, flight_cfg, classes):
    """Degradation per unit [U, C] and one flight per (unit, cycle) [U, C, T]."""
    c_max = deg_cfg.max_eol_cycle
    deg = jax.vmap(lambda k, fc: sample_unit_degradation(k, c_max, deg_cfg, fc))(
        jax.random.split(key_deg, classes.shape[0]), classes
    )
    keys = jax.random.split(key_flight, (classes.shape[0], c_max))
    flights = jax.vmap(
        lambda ku, fc: jax.vmap(lambda k: sample_flight(k, fc, flight_cfg))(ku)
    )(keys, classes)
    return deg, flights


def make_scenario(cfg: ScenarioConfig):
    """``scenario(keys [4]) -> FleetRows`` for :func:`~jaxcal.diagnosis.data.synthetic.
    make_synthetic_data` (keys: flight class, degradation, flights, kept rows)."""

    def scenario(keys) -> FleetRows:
        key_class, key_deg, key_flight, key_rows = keys
        deg_cfg = DegradationConfig(degrading=cfg.declared)
        classes = jax.random.randint(key_class, (cfg.num_units,), 1, 4)
        deg, flights = _sample_fleet(key_deg, key_flight, deg_cfg, cfg.flight, classes)
        scores = jnp.where(
            flights.mask, jax.random.uniform(key_rows, flights.mask.shape), -1.0
        )
        picks = np.asarray(jnp.argsort(-scores, axis=-1)[..., : cfg.rows_per_cycle])
        eol = np.asarray(deg.eol_cycle)
        rows = [
            (u, c, k)
            for u in range(cfg.num_units)
            for c in range(0, int(eol[u]), cfg.cycle_stride)
            for k in picks[u, c]
        ]
        u_i, c_i, k_i = (np.array(a) for a in zip(*rows, strict=True))
        return FleetRows(
            w=np.asarray(flights.w)[u_i, c_i, k_i],
            theta=np.asarray(deg.theta)[u_i, c_i].copy(),
            unit=u_i + 1,
            cycle=np.asarray(deg.cycle)[u_i, c_i],
            health=np.asarray(deg.health)[u_i, c_i],
        )

    return scenario
