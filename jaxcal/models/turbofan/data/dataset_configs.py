"""Static configuration of the paper's data sets and their named presets.

:class:`DatasetConfig` says everything
:func:`jaxcal.models.turbofan.data.builders.build_dataset` needs: which engine, which
builder (a run-to-failure ``"fleet"`` or a set of fault ``"scenarios"``), sizes, seed,
noise variants and chunking. :data:`DATASETS` holds the paper's two data sets (Table 1)
and a tiny preset for tests and smoke runs:

* ``cmapss``, Dataset #1 (d = 1): ten run-to-failure units of the ``cmapss`` engine
  in which only ``HPT_eff_mod`` degrades. Units 1, 4, 7 and 9 fly flight class 1
  (shorter, lower flights: the paper's labelled, non-representative E2E training
  units); the others fly classes 2 and 3, giving the 4/3/3 class mix of N-CMAPSS DS01.
  Dev units 1-6, test units 7-10 (as DS01). The 1 Hz flights are subsampled every 18 s:
  about 0.5 M samples.
* ``agtf30``, Dataset #2 (d = 4): the ``agtf30`` engine, three 5,000 s cruise-band
  flights at 1 Hz and the full factorial design of 6 levels (0 to -2 %) of HPT_eff,
  HPT_flow, LPT_eff and LPT_flow: 6^4 = 1,296 scenarios, each one "unit" flying one of
  the three flights (about 6.5 M samples). The paper has 1,315 scenarios from level sets
  it does not publish; no full factorial of four modifiers gives 1,315 (= 5 x 263), so
  the nearest regular design is used (see ``jaxcal.models.turbofan.data.degradation``).
  Scenarios are split 80/20 into dev/test by a seeded permutation.
* ``tiny``: a Dataset #1-like fleet of three short-lived units, a few hundred samples.

The config is hashable and never mutated; CLIs change it with
:func:`jaxcal.settings.parse_overrides` (``seed=3``, ``sensor_snr_db=70``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

from jaxcal.models.turbofan.data.degradation import DEFAULT_FACTORIAL_LEVELS
from jaxcal.models.turbofan.physics.configs import NOMINAL
from jaxcal.models.turbofan.physics.constants import (
    HEALTH_NAMES,
    MEASURED_SENSOR_NAMES,
    SENSOR_NAMES,
)

KINDS: tuple[str, ...] = ("fleet", "scenarios")
TURBINE_MODIFIERS: tuple[str, ...] = tuple(DEFAULT_FACTORIAL_LEVELS)
# AGTF30-like instrumentation (datasets.md): the paper's n = 8 observed sensors.
AGTF30_SENSORS: tuple[str, ...] = (
    "Nf",
    "Nc",
    "T24",
    "P24",
    "T30",
    "Ps30",
    "T48",
    "P50",
)


@dataclasses.dataclass(frozen=True)
class DatasetConfig:
    """Everything that defines a generated data set (hashable, static).

    Fields marked (fleet) are used only when ``kind == "fleet"``, fields marked
    (scenarios) only when ``kind == "scenarios"``.
    """

    name: str = "cmapss"  # preset name, written to the file's attributes
    # "fleet": run-to-failure units (Dataset #1); "scenarios": fault grid (Dataset #2)
    kind: Literal["fleet", "scenarios"] = "fleet"
    engine: Literal["cmapss", "agtf30"] = "cmapss"  # configuration for load_engine
    seed: int = 0  # root PRNG seed; the same seed gives byte-identical arrays
    # modifiers that degrade (fleet) / that the factorial design varies (scenarios)
    degrading: tuple[str, ...] = ("HPT_eff_mod",)
    dt_s: float = 18.0  # sampling period [s] of the 1 Hz flights (1 = no subsampling)
    # sensors a calibration method observes (metadata; the file always holds all 28).
    # Default: the 14 N-CMAPSS X_s (the paper's n = 20 for Dataset #1 is not broken
    # down); agtf30: the 8 AGTF30-like sensors of datasets.md (paper: n = 8).
    observed_sensors: tuple[str, ...] = MEASURED_SENSOR_NAMES
    # --- fleet
    num_units: int = 10  # number of run-to-failure units, ids 1..num_units
    # flight class (1, 2, 3) of unit 1, 2, ...; repeated cyclically up to num_units
    flight_classes: tuple[int, ...] = (1, 2, 3, 1, 3, 2, 1, 3, 1, 2)
    dev_units: tuple[int, ...] = (1, 2, 3, 4, 5, 6)  # the other units are test units
    life_scale: float = 1.0  # scales onset / end-of-life cycle ranges (tiny: 0.1)
    cycles_per_block: int = 8  # flights generated per jitted call (memory bound)
    # --- scenarios
    num_flights: int = 3  # distinct cruise-band flight trajectories
    flight_steps: int = 5000  # samples per flight (5,000 s at 1 Hz in the paper)
    fault_levels: tuple[float, ...] = DEFAULT_FACTORIAL_LEVELS["HPT_eff_mod"]
    num_scenarios: int | None = None  # seeded subset of the design (None: all)
    test_fraction: float = 0.2  # share of scenarios in the test split
    scenarios_per_block: int = 8  # scenarios generated per jitted call
    # --- noise variants (paper's robustness tables); applied in this order
    output_bias: float = 1.0  # model-output bias: x * output_bias (paper: 1.02)
    output_noise_sigma: float = 0.0  # x + N(0, sigma) on normalised outputs (0.1)
    sensor_snr_db: float | None = None  # white noise on X_s at this SNR (70); None: off
    # --- execution
    chunk_size: int = 8192  # rows per engine call and per appended file block
    max_retries: int = 3  # warm-started re-solves of non-converged samples

    def __post_init__(self):
        def fail(field, expected):
            got = getattr(self, field)
            raise ValueError(f"DatasetConfig.{field} must be {expected}, got {got!r}")

        if self.kind not in KINDS:
            fail("kind", f"one of {KINDS}")
        if self.engine not in NOMINAL:
            fail("engine", f"one of {tuple(NOMINAL)}")
        unknown = [n for n in self.degrading if n not in HEALTH_NAMES]
        if (
            not self.degrading
            or unknown
            or len(set(self.degrading)) < len(self.degrading)
        ):
            fail("degrading", f"distinct names from {HEALTH_NAMES}")
        if not self.observed_sensors or any(
            s not in SENSOR_NAMES for s in self.observed_sensors
        ):
            fail("observed_sensors", f"names from {SENSOR_NAMES}")
        if not (math.isfinite(self.dt_s) and self.dt_s > 0):
            fail("dt_s", "a finite number of seconds > 0")
        for field in ("chunk_size", "cycles_per_block", "scenarios_per_block"):
            if getattr(self, field) < 1:
                fail(field, "an integer >= 1")
        if self.max_retries < 0:
            fail("max_retries", "an integer >= 0")
        if self.num_units < 1:
            fail("num_units", "an integer >= 1")
        if not self.flight_classes or any(
            c not in (1, 2, 3) for c in self.flight_classes
        ):
            fail("flight_classes", "a non-empty tuple of classes 1, 2, 3")
        if not self.dev_units or any(
            not 1 <= u <= self.num_units for u in self.dev_units
        ):
            fail("dev_units", f"a non-empty tuple of unit ids in 1..{self.num_units}")
        if not (math.isfinite(self.life_scale) and self.life_scale > 0):
            fail("life_scale", "a finite number > 0")
        if self.num_flights < 1 or self.flight_steps < 1:
            fail("num_flights", "with flight_steps, an integer >= 1")
        if not self.fault_levels or len(set(self.fault_levels)) < len(
            self.fault_levels
        ):
            fail("fault_levels", "a non-empty tuple of distinct numbers")
        if self.num_scenarios is not None and not (
            1 <= self.num_scenarios <= self.design_size
        ):
            fail("num_scenarios", f"None or an integer in 1..{self.design_size}")
        if not 0.0 <= self.test_fraction < 1.0:
            fail("test_fraction", "a number in [0, 1)")
        if not (math.isfinite(self.output_bias) and self.output_bias > 0):
            fail("output_bias", "a finite number > 0 (1.0 = no bias)")
        if not (
            math.isfinite(self.output_noise_sigma) and self.output_noise_sigma >= 0
        ):
            fail("output_noise_sigma", "a finite number >= 0 (0 = no noise)")
        if self.sensor_snr_db is not None and not math.isfinite(self.sensor_snr_db):
            fail("sensor_snr_db", "None or a finite SNR in dB")

    @property
    def sample_rate_hz(self) -> float:
        """Rows per second within a flight (the file's ``sample_rate_hz``)."""
        return 1.0 / self.dt_s

    @property
    def design_size(self) -> int:
        """Scenarios in the full factorial design: levels ** modifiers."""
        return len(self.fault_levels) ** len(self.degrading)

    @property
    def unit_classes(self) -> tuple[int, ...]:
        """Flight class of units 1..num_units (``flight_classes`` repeated)."""
        k = len(self.flight_classes)
        return tuple(self.flight_classes[u % k] for u in range(self.num_units))

    @property
    def test_units(self) -> tuple[int, ...]:
        """Fleet units not in ``dev_units``, ascending."""
        return tuple(u for u in range(1, self.num_units + 1) if u not in self.dev_units)

    @property
    def has_noise(self) -> bool:
        """True when any noise / bias variant changes the engine outputs."""
        return (
            self.output_bias != 1.0
            or self.output_noise_sigma > 0
            or self.sensor_snr_db is not None
        )


DATASETS: dict[str, DatasetConfig] = {
    "cmapss": DatasetConfig(),
    "agtf30": DatasetConfig(
        name="agtf30",
        kind="scenarios",
        engine="agtf30",
        degrading=TURBINE_MODIFIERS,
        dt_s=1.0,
        observed_sensors=AGTF30_SENSORS,
    ),
    "tiny": DatasetConfig(
        name="tiny",
        num_units=3,
        flight_classes=(1, 1, 2),
        dev_units=(1, 2),
        dt_s=300.0,
        life_scale=0.1,
        cycles_per_block=4,
        num_flights=2,
        flight_steps=20,
        num_scenarios=6,
        scenarios_per_block=2,
        chunk_size=128,
    ),
}
