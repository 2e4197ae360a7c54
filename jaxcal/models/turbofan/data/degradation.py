"""Jittable health-degradation generators: N-CMAPSS-like run-to-failure units and
factorial fault scenarios, plus the per-cycle -> per-sample expansion used by builders.

Run-to-failure model. Arias Chao et al. (2021) describe a random initial degradation, a
linear normal phase with a fleet-varying rate, a smooth transition at t_s to a steeper
abnormal phase, and failure when the health index reaches 0 (data_facts.md section 4).
Their abnormal equation is not public, so the abnormal term is the C-MAPSS 2008
exponential form exp(a t^b) of Saxena et al. (2008), shifted to start at the onset::

    h(t) = 1 - d - r t - (exp(a (t - t_s)_+^b) - 1),   b > 1,

which has value and slope continuous at t_s (smooth transition) and a slope that grows
after it. Given the sampled end of life L, r and a are solved so that h(L) = 0 exactly:
r = u (1 - d) / L puts a share u of the health loss on the linear process, and
a = log(1 + (1 - u)(1 - d)) / (L - t_s)^b gives the rest to the abnormal term. The
degrading health modifiers are theta_j = m_j (1 - h), so theta_j(L) = m_j, the sampled
end-of-life value (the initial degradation d shows as a unit-specific offset m_j d at
cycle 0).
No process noise is added, so h is strictly decreasing until L.
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from jaxcal.models.turbofan.data.ground_truth import (
    DEFAULT_EOL_THETA_RANGE,
    EOL_CYCLES_BY_CLASS,
    ONSET_CYCLES_BY_CLASS,
)
from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES, health_index
from jaxcal.typedefs import Array, PRNGKey

Range = tuple[float, float]

# Dataset #2 design: 6 levels of each turbine modifier, 0 % to -2 % in 0.4 % steps, so
# 6^4 = 1296 scenarios (the paper has 1315; its level sets are not published). -2 %
# covers the median EOL change of these modifiers in N-CMAPSS (HPT_eff -0.008, HPT_flow
# -0.008, LPT_eff -0.008, LPT_flow -0.012; ground_truth.py) and the HPT_eff-only maximum
# -0.0185. The zero level makes the design hold single, double, triple and quadruple
# faults and, as row 0, the healthy engine.
DEFAULT_FACTORIAL_LEVELS: dict[str, tuple[float, ...]] = {
    name: (0.0, -0.004, -0.008, -0.012, -0.016, -0.020)
    for name in ("HPT_eff_mod", "HPT_flow_mod", "LPT_eff_mod", "LPT_flow_mod")
}


@dataclasses.dataclass(frozen=True)
class DegradationConfig:
    """Static settings of the run-to-failure generator (defaults: ground_truth.py)."""

    degrading: tuple[str, ...] = ("HPT_eff_mod",)  # modifiers driven by health index
    # EOL value (most negative, least negative) per degrading modifier; None = defaults
    eol_theta_range: tuple[Range, ...] | None = None
    initial_degradation: Range = (0.0, 0.1)  # d: ~10 % of the health index (NASA doc)
    onset_cycles: tuple[tuple[int, int], ...] = ONSET_CYCLES_BY_CLASS  # t_s per Fc
    eol_cycles: tuple[tuple[int, int], ...] = EOL_CYCLES_BY_CLASS  # L per Fc
    min_abnormal_cycles: int = 10  # L >= t_s + this
    # u and b are set by eye (the real abnormal law is unpublished): a visible linear
    # phase, then a clearly steeper one (mean slope after t_s >= ~2x the one before).
    normal_share: Range = (0.15, 0.35)  # u: share of the EOL loss from the linear phase
    abnormal_exponent: Range = (1.1, 1.6)  # b of exp(a t^b); b > 1 for a smooth onset
    initial_offset: float = 0.0  # non-degrading modifiers: offset ~ U(-this, 0)

    def __post_init__(self):
        health_index(self.degrading)  # ValueError for unknown names
        if len(set(self.degrading)) != len(self.degrading):
            raise ValueError(
                f"DegradationConfig.degrading has repeats: {self.degrading}"
            )
        if self.eol_theta_range is not None and len(self.eol_theta_range) != len(
            self.degrading
        ):
            raise ValueError(
                "DegradationConfig.eol_theta_range needs one (lo, hi) per degrading "
                f"modifier {self.degrading}, got {self.eol_theta_range}"
            )
        if len(self.onset_cycles) != len(self.eol_cycles) or not self.onset_cycles:
            raise ValueError(
                "DegradationConfig.onset_cycles and eol_cycles need one (lo, hi) per "
                "flight class, with the same number of classes"
            )
        for name in ("onset_cycles", "eol_cycles", "theta_ranges"):
            for lo, hi in getattr(self, name):
                if not lo <= hi:
                    raise ValueError(
                        f"DegradationConfig.{name}: ({lo}, {hi}) has lo > hi"
                    )
        if min(lo for lo, _ in self.onset_cycles) < 1:
            raise ValueError("DegradationConfig.onset_cycles must be >= 1")
        if not 0.0 <= self.initial_degradation[0] <= self.initial_degradation[1] < 1.0:
            raise ValueError("DegradationConfig.initial_degradation must lie in [0, 1)")
        if not 0.0 < self.normal_share[0] <= self.normal_share[1] < 1.0:
            raise ValueError("DegradationConfig.normal_share must lie in (0, 1)")
        if not 1.0 < self.abnormal_exponent[0] <= self.abnormal_exponent[1]:
            raise ValueError("DegradationConfig.abnormal_exponent must be > 1")

    @property
    def theta_ranges(self) -> tuple[Range, ...]:
        """EOL value range of each degrading modifier (explicit or ground-truth)."""
        if self.eol_theta_range is not None:
            return tuple(self.eol_theta_range)
        return tuple(DEFAULT_EOL_THETA_RANGE[name] for name in self.degrading)

    @property
    def max_eol_cycle(self) -> int:
        """Longest possible life: the smallest valid ``num_cycles_max``."""
        return max(
            max(eol_hi, onset_hi + self.min_abnormal_cycles)
            for (_, onset_hi), (_, eol_hi) in zip(
                self.onset_cycles, self.eol_cycles, strict=True
            )
        )


class UnitDegradation(NamedTuple):
    """One unit's life padded to ``C_max`` cycles (padding repeats the EOL state)."""

    cycle: Array  # [C] int32, 1-based cycle numbers
    health: Array  # [C] health index h, 1 - d at cycle 0, exactly 0 at EOL
    theta: Array  # [C, 10] health modifiers (HEALTH_NAMES order)
    hs: Array  # [C] int32, 1 before t_s, 0 from t_s on
    rul: Array  # [C] int32, eol_cycle - cycle (0 on the last flight and on padding)
    mask: Array  # [C] bool, cycle <= eol_cycle
    eol_cycle: Array  # [] int32, first cycle with h = 0
    onset_cycle: Array  # [] int32, t_s


class SampleRows(NamedTuple):
    """Flattened N-CMAPSS rows of ``R`` samples; ``mask`` marks the real ones."""

    w: Array  # [R, 4]
    theta: Array  # [R, 10]
    unit: Array  # [R] int32
    cycle: Array  # [R] int32
    fc: Array  # [R] int32
    hs: Array  # [R] int32
    rul: Array  # [R] int32
    mask: Array  # [R] bool


def _uniform(key: PRNGKey, bounds, shape=()) -> Array:
    bounds = jnp.asarray(bounds, dtype=float)
    return bounds[..., 0] + (bounds[..., 1] - bounds[..., 0]) * jax.random.uniform(
        key, shape
    )


def sample_unit_degradation(
    key: PRNGKey, num_cycles_max: int, cfg: DegradationConfig, flight_class
) -> UnitDegradation:
    """Sample one run-to-failure unit (model in the module docstring).

    Args:
        key: PRNG key; the same key gives the same unit.
        num_cycles_max: C_max (static), at least ``cfg.max_eol_cycle``.
        cfg: static :class:`DegradationConfig`.
        flight_class: 1, 2 or 3 (Python int or traced int32 scalar); it sets the onset
            and EOL ranges (longer flights reach onset in fewer cycles).

    Returns:
        :class:`UnitDegradation` with per-cycle arrays of length C_max.
    """
    num_classes = len(cfg.onset_cycles)
    if num_cycles_max < cfg.max_eol_cycle:
        raise ValueError(
            f"num_cycles_max must be >= {cfg.max_eol_cycle} (longest possible life), "
            f"got {num_cycles_max}"
        )
    if (
        isinstance(flight_class, numbers.Integral)
        and not 1 <= flight_class <= num_classes
    ):
        raise ValueError(
            f"flight_class must be in 1..{num_classes}, got {flight_class}"
        )
    idx = jnp.clip(jnp.asarray(flight_class, jnp.int32) - 1, 0, num_classes - 1)
    key_d, key_onset, key_eol, key_shape, key_mag, key_offset = jax.random.split(key, 6)

    d = _uniform(key_d, cfg.initial_degradation)
    onset_bounds = jnp.asarray(cfg.onset_cycles, jnp.int32)[idx]
    onset = jax.random.randint(key_onset, (), onset_bounds[0], onset_bounds[1] + 1)
    eol_bounds = jnp.asarray(cfg.eol_cycles, jnp.int32)[idx]
    eol = jax.random.randint(key_eol, (), eol_bounds[0], eol_bounds[1] + 1)
    eol = jnp.maximum(eol, onset + cfg.min_abnormal_cycles)
    key_share, key_exp = jax.random.split(key_shape)
    share = _uniform(key_share, cfg.normal_share)
    b = _uniform(key_exp, cfg.abnormal_exponent)
    rate = share * (1.0 - d) / eol
    a = jnp.log1p((1.0 - share) * (1.0 - d)) / (eol - onset).astype(d.dtype) ** b

    cycle = jnp.arange(1, num_cycles_max + 1, dtype=jnp.int32)
    t = jnp.minimum(cycle, eol).astype(d.dtype)
    excess = jnp.expm1(a * jnp.maximum(t - onset, 0.0) ** b)
    # h(L) = 0 holds analytically; pin it so that EOL is exact in any precision.
    health = jnp.where(cycle >= eol, 0.0, 1.0 - d - rate * t - excess)

    magnitude = _uniform(key_mag, cfg.theta_ranges, (len(cfg.degrading),))
    offset = -cfg.initial_offset * jax.random.uniform(key_offset, (len(HEALTH_NAMES),))
    theta = jnp.broadcast_to(offset, (num_cycles_max, len(HEALTH_NAMES)))
    theta = theta.at[:, jnp.asarray(health_index(cfg.degrading))].set(
        (1.0 - health)[:, None] * magnitude
    )
    mask = cycle <= eol
    return UnitDegradation(
        cycle=cycle,
        health=health,
        theta=theta,
        hs=(cycle < onset).astype(jnp.int32),
        rul=jnp.where(mask, eol - cycle, 0).astype(jnp.int32),
        mask=mask,
        eol_cycle=eol.astype(jnp.int32),
        onset_cycle=onset.astype(jnp.int32),
    )


def slice_cycles(deg: UnitDegradation, start, size: int) -> UnitDegradation:
    """Cycles ``start .. start + size - 1`` (0-based; ``start`` may be traced).

    Lets a builder generate a long unit chunk by chunk; scalar fields are kept.
    """
    take = lambda x: lax.dynamic_slice_in_dim(x, start, size, axis=0)  # noqa: E731
    return deg._replace(
        cycle=take(deg.cycle),
        health=take(deg.health),
        theta=take(deg.theta),
        hs=take(deg.hs),
        rul=take(deg.rul),
        mask=take(deg.mask),
    )


def theta_per_sample(theta_cycles: Array, sample_mask: Array) -> tuple[Array, Array]:
    """Hold each cycle's theta over all samples of its flight, flattened cycle-major.

    Args:
        theta_cycles: [C, P] theta per cycle (constant within a flight).
        sample_mask: [C, T] validity of the samples of each cycle's flight.

    Returns:
        (theta [C*T, P], mask [C*T]); row c*T + k is sample k of cycle c.
    """
    num_cycles, num_steps = sample_mask.shape
    if theta_cycles.ndim != 2 or theta_cycles.shape[0] != num_cycles:
        raise ValueError(
            f"theta_cycles must be [C={num_cycles}, P], got shape {theta_cycles.shape}"
        )
    theta = jnp.broadcast_to(
        theta_cycles[:, None, :], (num_cycles, num_steps, theta_cycles.shape[1])
    )
    return theta.reshape(num_cycles * num_steps, -1), sample_mask.reshape(-1)


def sample_rows(
    w: Array, sample_mask: Array, deg: UnitDegradation, unit, flight_class
) -> SampleRows:
    """N-CMAPSS rows (w, theta, unit, cycle, Fc, hs, rul) of one unit's flights.

    Pure and static-shaped: vmap it over units for a chunk, then drop the rows with
    ``mask == False`` on the host (``x[mask]`` in numpy) before writing.

    Args:
        w: [C, T, 4] conditions of the flights of C cycles (vmapped ``sample_flight``).
        sample_mask: [C, T] flight validity masks.
        deg: the unit's degradation for the same C cycles (see :func:`slice_cycles`).
        unit: [] unit id.
        flight_class: [] the unit's flight class.

    Returns:
        :class:`SampleRows` of R = C*T rows; padded samples and cycles after EOL are
        masked out.
    """
    if (
        w.ndim != 3
        or w.shape[:2] != sample_mask.shape
        or deg.cycle.shape[0] != w.shape[0]
    ):
        raise ValueError(
            "sample_rows needs w [C, T, 4], sample_mask [C, T] and deg with C cycles; "
            "got "
            f"w {w.shape}, sample_mask {sample_mask.shape}, deg.cycle {deg.cycle.shape}"
        )
    num_steps = w.shape[1]
    theta, mask = theta_per_sample(deg.theta, sample_mask & deg.mask[:, None])
    per_sample = lambda x: jnp.repeat(x, num_steps, axis=0)  # noqa: E731
    unit_id = jnp.full(mask.shape, unit, jnp.int32)
    return SampleRows(
        w=w.reshape(-1, w.shape[-1]),
        theta=theta,
        unit=unit_id,
        cycle=per_sample(deg.cycle),
        fc=jnp.full(mask.shape, flight_class, jnp.int32),
        hs=per_sample(deg.hs),
        rul=per_sample(deg.rul),
        mask=mask,
    )


def factorial_fault_scenarios(
    levels: Mapping[str, Sequence[float]] | None = None, *, base=None
) -> Array:
    """Full factorial design of discrete fault levels (the paper's Dataset #2).

    Args:
        levels: modifier name -> distinct levels; None uses
            :data:`DEFAULT_FACTORIAL_LEVELS` (4 turbine modifiers x 6 levels = 1296).
        base: optional [10] theta added to every scenario (other modifiers stay at it).

    Returns:
        [M, 10] theta, M = prod(len(levels[name])), in ``itertools.product`` order
        (the first name varies slowest).
    """
    levels = DEFAULT_FACTORIAL_LEVELS if levels is None else levels
    if not levels:
        raise ValueError("factorial_fault_scenarios: levels must name >= 1 modifier")
    names = list(levels)
    columns = health_index(names)
    for name in names:
        values = [float(v) for v in levels[name]]
        if not values or len(set(values)) != len(values):
            raise ValueError(
                f"factorial_fault_scenarios: levels[{name!r}] must be a non-empty "
                f"sequence of distinct numbers, got {levels[name]}"
            )
    axes = jnp.meshgrid(*(jnp.asarray(levels[n], float) for n in names), indexing="ij")
    grid = jnp.stack([a.reshape(-1) for a in axes], axis=-1)  # [M, k]
    base = jnp.zeros(len(HEALTH_NAMES)) if base is None else jnp.asarray(base, float)
    if base.shape != (len(HEALTH_NAMES),):
        raise ValueError(f"base must have shape [10], got {base.shape}")
    theta = jnp.broadcast_to(base, (grid.shape[0], len(HEALTH_NAMES)))
    return theta.at[:, jnp.asarray(columns)].add(grid)
