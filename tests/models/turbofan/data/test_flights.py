"""Flight-profile and cruise-band generators: envelope, durations, determinism, jit."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.models.turbofan.data.flights import (
    CruiseBand,
    FlightConfig,
    sample_cruise_band,
    sample_flight,
    smooth_noise,
)
from jaxcal.models.turbofan.physics.atmosphere import (
    isa_static,
    isa_total_temperature,
    ram_ratio,
)


def delta_isa(alt_ft, mach, t2_r):
    """Ambient temperature deviation from ISA implied by a measured T2 [degR] (the
    test's reference: the library schedules on T2 itself)."""
    t_amb, _ = isa_static(alt_ft)
    return jnp.asarray(t2_r) / ram_ratio(mach) - t_amb


CFG = FlightConfig(dt_s=30.0)  # T_max = 840: small but still whole flights
NUM_FLIGHTS = 24


# One compiled sampler for the whole module: compiling is the slow part on a busy CPU.
def _sample_batch(keys, classes):
    return jax.vmap(lambda k, c: sample_flight(k, c, CFG))(keys, classes)


_sample_fleet = jax.jit(chex.assert_max_traces(_sample_batch, n=1))


def _fleet(seed: int):
    keys = jax.random.split(jax.random.key(seed), NUM_FLIGHTS)
    classes = jnp.tile(jnp.arange(1, 4), NUM_FLIGHTS // 3)
    return keys, classes, jax.tree.map(np.asarray, _sample_fleet(keys, classes))


@pytest.fixture(scope="module")
def fleet_flights():
    _, classes, out = _fleet(0)
    return out, np.asarray(classes)


def test_vmap_over_keys_gives_static_shapes(fleet_flights):
    out, _ = fleet_flights
    assert CFG.num_steps == 840
    chex.assert_shape(out.w, (NUM_FLIGHTS, CFG.num_steps, 4))
    chex.assert_shape(out.mask, (NUM_FLIGHTS, CFG.num_steps))
    chex.assert_shape(out.duration_s, (NUM_FLIGHTS,))
    chex.assert_tree_all_finite(out.w)


def test_recorded_samples_stay_in_the_envelope(fleet_flights):
    out, _ = fleet_flights
    m = out.mask
    alt, mach, tra, t2 = (out.w[..., j][m] for j in range(4))
    assert alt.min() >= CFG.min_alt_ft and alt.max() <= CFG.max_alt_ft
    assert mach.min() >= 0.2 and mach.max() <= 0.75
    assert tra.min() >= 20.0 and tra.max() <= 100.0
    # N-CMAPSS notebook envelope: ceiling 17 kft at Mach 0.2 rising to 40 kft at 0.4
    assert np.all(alt <= 17_000.0 + (40_000.0 - 17_000.0) * (mach - 0.2) / 0.2 + 1e-6)
    # T2 is an ISA total temperature on an off-standard day of at most +-25 degR
    dev = np.asarray(delta_isa(alt, mach, t2))
    assert np.abs(dev).max() <= CFG.delta_t_limit_r + 1e-6


def test_realised_ranges_resemble_paper_table(fleet_flights):
    out, _ = fleet_flights
    m = out.mask
    alt, mach, tra = (out.w[..., j][m] for j in range(3))
    # paper Table 1, Dataset #1: alt 10.0k-35.0k, Mach 0.26-0.75, TRA 23.6-87.8
    assert alt.min() < 10_500.0 and alt.max() > 33_000.0
    assert mach.min() < 0.40 and mach.max() > 0.70
    assert tra.min() < 36.0 and tra.max() > 78.0


def test_flight_class_sets_duration_and_cruise_level(fleet_flights):
    out, classes = fleet_flights
    for c, (lo, hi) in enumerate(CFG.class_hours, start=1):
        total = out.flight_time_s[classes == c] / 3600.0
        assert total.min() >= lo and total.max() <= hi
        recorded = out.duration_s[classes == c]
        below = out.flight_time_s[classes == c] - recorded
        assert below.min() >= CFG.below_floor_s[0] - 1e-6
    # the mask covers exactly the recorded time and is a prefix
    np.testing.assert_allclose(
        out.mask.sum(1) * CFG.dt_s, out.duration_s, atol=CFG.dt_s
    )
    assert np.all(np.diff(out.mask.astype(int), axis=1) <= 0)
    # shorter flights cruise lower
    top = np.where(out.mask, out.w[..., 0], 0.0).max(1)
    assert top[classes == 1].mean() < top[classes == 3].mean() - 3000.0


def test_padding_repeats_last_recorded_sample(fleet_flights):
    out, classes = fleet_flights
    i = int(np.argmin(out.duration_s))  # a short flight has padding
    n = int(out.mask[i].sum())
    assert n < CFG.num_steps
    np.testing.assert_array_equal(
        out.w[i, n:], np.broadcast_to(out.w[i, n - 1], out.w[i, n:].shape)
    )


def test_trajectories_are_smooth_but_noisy(fleet_flights):
    out, _ = fleet_flights
    rates = np.diff(out.w[..., :3], axis=1) / CFG.dt_s  # per second
    valid = out.mask[:, 1:]
    # climb / descent rates stay physical (< 4,000 ft/min), and so do accelerations
    # (0.003 Mach/s is about 2 kt/s, 0.1 g)
    assert np.abs(rates[..., 0])[valid].max() < 4000.0 / 60.0
    assert np.abs(rates[..., 1])[valid].max() < 3e-3
    # but it is not a clean piecewise profile: cruise Mach and TRA wiggle
    assert np.std(rates[..., 1][valid]) > 1e-6 and np.std(rates[..., 2][valid]) > 1e-3


def test_same_key_same_flight_different_key_different_flight(fleet_flights):
    out, _ = fleet_flights
    _, _, again = _fleet(0)  # same keys, also checks that nothing recompiles
    _, _, other = _fleet(1)
    np.testing.assert_array_equal(out.w, again.w)
    np.testing.assert_array_equal(out.mask, again.mask)
    assert not np.allclose(out.w, other.w)
    assert (
        len({w.tobytes() for w in out.w}) == NUM_FLIGHTS
    )  # keys within a batch differ


def test_jit_matches_eager(fleet_flights):
    out, classes = fleet_flights
    keys = jax.random.split(jax.random.key(0), NUM_FLIGHTS)
    eager = sample_flight(keys[1], int(classes[1]), CFG)
    np.testing.assert_allclose(eager.w, out.w[1], rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(eager.mask, out.mask[1])
    np.testing.assert_allclose(eager.duration_s, out.duration_s[1], rtol=1e-12)


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="flight_class"):
        sample_flight(jax.random.key(0), 4, CFG)
    with pytest.raises(ValueError, match="dt_s"):
        FlightConfig(dt_s=0.0)
    with pytest.raises(ValueError, match="class_hours"):
        FlightConfig(class_hours=((3.0, 1.0),))
    with pytest.raises(ValueError, match="CruiseBand.mach"):
        CruiseBand(mach=(0.8, 0.7))


def test_smooth_noise_is_stationary_unit_variance_and_correlated():
    noise = jax.jit(lambda k: smooth_noise(k, 200, 3000, 1.0, 20.0))
    x = np.asarray(noise(jax.random.key(1)))
    # stationary from the first sample on: no start-up transient
    assert abs(x[0].std() - 1.0) < 0.05 and abs(x[-1].std() - 1.0) < 0.05
    lag1 = np.mean(x[1:] * x[:-1]) / np.mean(x * x)
    assert lag1 > 0.99  # second-order low-pass: very smooth at tau = 20 samples


def test_cruise_band_stays_in_band_and_moves_across_it():
    band = CruiseBand()
    out = jax.jit(lambda k: sample_cruise_band(k, 5000, band))(jax.random.key(2))
    w = np.asarray(out.w)
    chex.assert_shape(w, (5000, 4))
    assert out.mask.all() and float(out.duration_s) == 5000.0
    for j, (lo, hi) in enumerate((band.alt_ft, band.mach, band.tra)):
        assert w[:, j].min() >= lo - 1e-9 and w[:, j].max() <= hi + 1e-9
        assert np.ptp(w[:, j]) > 0.5 * (hi - lo)  # explores the band
        assert np.abs(np.diff(w[:, j])).max() < 0.1 * (hi - lo)  # no jumps
    t2_isa = np.asarray(isa_total_temperature(w[:, 0], w[:, 1]))
    assert np.abs(w[:, 3] - t2_isa).max() < 1.2 * (band.delta_t_day_r + 5.0)
