"""Block least squares, spline bases, data preparation and noise estimation (numpy)."""

import dataclasses

import numpy as np
import pytest
from scipy import stats as sps

from jaxcal.diagnosis.data.prepare import prepare_data as _prepare
from jaxcal.diagnosis.data.prepare import spline_basis
from jaxcal.diagnosis.fitting.joint import GramStats, schur_solve
from jaxcal.diagnosis.fitting.ranking import log10_chi2_sf
from jaxcal.diagnosis.residuals.noise_fit import fit_noise, quantised
from jaxcal.models import load
from jaxcal.models.turbofan.data.datasets import dataset_from_record
from jaxcal.models.turbofan.data.record import Record


def prepare_data(record, **kwargs):
    """The turbofan Record through the Dataset adapter (as the pipeline does)."""
    return _prepare(
        dataset_from_record(record), load("cmapss"), dropped_rows=record.dropped_rows,
        **kwargs,
    )  # fmt: skip


def _random_blocks(rng, units=3, rows=40, local=4, glob=2):
    z = [rng.normal(size=(rows, local + glob)) * 10.0 for _ in range(units)]
    r = [rng.normal(size=rows) for _ in range(units)]
    stats = GramStats(
        gram=np.stack([zu.T @ zu for zu in z]),
        score=np.stack([zu.T @ ru for zu, ru in zip(z, r, strict=True)]),
        ssr=float(sum(ru @ ru for ru in r)),
        num_local=local,
    )
    dense = np.zeros((units * rows, units * local + glob))
    for u, zu in enumerate(z):
        dense[u * rows : (u + 1) * rows, u * local : (u + 1) * local] = zu[:, :local]
        dense[u * rows : (u + 1) * rows, units * local :] = zu[:, local:]
    return stats, dense, np.concatenate(r)


def test_schur_solve_equals_dense_least_squares():
    rng = np.random.default_rng(0)
    stats, dense, r = _random_blocks(rng)
    sol = schur_solve(stats, range(4), range(2))
    expected = np.linalg.lstsq(dense, r, rcond=None)[0]
    np.testing.assert_allclose(
        sol.local_step.ravel(), expected[:12], rtol=1e-6, atol=1e-9
    )
    np.testing.assert_allclose(sol.global_step, expected[12:], rtol=1e-6, atol=1e-9)
    resid = r - dense @ expected
    np.testing.assert_allclose(sol.reduction, r @ r - resid @ resid, rtol=1e-6)


def test_schur_solve_subsets_of_columns():
    rng = np.random.default_rng(1)
    stats, dense, r = _random_blocks(rng)
    # only local column 1 per unit and global column 0
    cols = [1, 5, 9, 12]
    expected = np.linalg.lstsq(dense[:, cols], r, rcond=None)[0]
    sol = schur_solve(stats, [1], [0])
    np.testing.assert_allclose(sol.local_step[:, 0], expected[:3], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(sol.global_step, expected[3:], rtol=1e-6, atol=1e-9)
    only_global = schur_solve(stats, [], [0, 1])
    ref = np.linalg.lstsq(dense[:, 12:], r, rcond=None)[0]
    np.testing.assert_allclose(only_global.global_step, ref, rtol=1e-8)


def test_spline_basis_is_a_partition_of_unity():
    cycle = np.arange(1, 81, dtype=float)
    for k in (1, 2, 3, 6):
        b = spline_basis(cycle, k)
        assert b.shape == (80, k)
        np.testing.assert_allclose(b.sum(1), 1.0, atol=1e-12)
        assert np.all(b >= -1e-15)
    np.testing.assert_allclose(spline_basis(np.array([5.0, 5.0]), 4)[:, 0], 1.0)
    with pytest.raises(ValueError, match="knots"):
        spline_basis(cycle, 0)


def _record(rng, n_per_unit=30):
    units = np.repeat([7, 3], n_per_unit)
    cycle = np.tile(np.arange(1, n_per_unit + 1), 2)
    order = rng.permutation(units.size)  # rows deliberately out of order
    w = np.stack(
        [
            np.full(units.size, 1e4),
            rng.uniform(0.3, 0.7, units.size),
            np.full(units.size, 80.0),
            np.full(units.size, 480.0),
        ],
        axis=1,
    )
    w[0, 1] = -0.0005  # jitter of a static condition below Mach 0
    x = np.stack(
        [
            rng.normal(1500, 4, units.size),
            rng.normal(2300, 1, units.size),
            np.full(units.size, 14.62),
            np.round(rng.normal(8, 0.5, units.size)),
        ],
        axis=1,
    )
    return Record(
        w=w[order],
        x=x[order],
        x_names=("T30", "Nf", "P2", "Nc"),
        theta=None,
        unit=units[order],
        cycle=cycle[order],
        flight_class=np.full(units.size, np.nan),
        hs=np.full(units.size, np.nan),
        rul=np.zeros(units.size, int),
    )


def test_prepare_data_sorts_selects_and_explains_exclusions():
    rng = np.random.default_rng(2)
    data = prepare_data(_record(rng), knots=4, candidate_knots=2)
    assert data.sensor_names == ("T30",)
    assert "controller" in data.excluded["Nf"]
    assert "constant" in data.excluded["P2"]
    assert "distinct" in data.excluded["Nc"]
    np.testing.assert_array_equal(data.unit_ids, [3, 7])
    np.testing.assert_array_equal(data.starts, [0, 30, 60])
    assert np.all(np.diff(data.cycle[:30]) > 0)
    assert data.basis.shape == (60, 4) and data.basis_candidate.shape == (60, 2)
    np.testing.assert_allclose(data.tau[:30], np.arange(30) / 100.0)
    assert data.w[:, 1].min() >= 0.0 and "Mach just outside" in data.notes[0]
    small = prepare_data(_record(rng), max_rows=20)
    assert 14 <= small.num_rows <= 22 and small.num_units == 2
    said = [n for n in small.notes if "rows used" in n]  # subsampling is said
    assert said == [f"{small.num_rows} of 60 rows used: one in 3 of each unit's rows "
                    "(max_rows=20; 0 or None keeps every row)"]  # fmt: skip
    assert not any("rows used" in n for n in data.notes)  # all rows: nothing said
    keep = np.arange(data.num_rows) >= 30
    only7 = data.take_rows(keep, "unit 3 dropped")
    np.testing.assert_array_equal(only7.unit_ids, [7])
    assert only7.num_units == 1 and only7.notes[-1] == "unit 3 dropped"


def test_prepare_data_rejects_unknown_sensor_and_bad_noise():
    rng = np.random.default_rng(3)
    with pytest.raises(ValueError, match="not in both"):
        prepare_data(_record(rng), sensors=["T48"])
    with pytest.raises(ValueError, match="no entry for outputs"):
        prepare_data(_record(rng), sensors=["T30"], noise_std={"T24": 1.0})


def test_noise_estimate_recovers_sigma_and_flags_rounding():
    rng = np.random.default_rng(4)
    rec = _record(rng, n_per_unit=200)
    data = prepare_data(rec, sensors=["T30"], noise_std={"T30": 1.0})
    smooth = 30.0 * np.sin(6.0 * data.w[:, 1])  # model misfit that varies with w
    resid = (smooth + 2.0 * rng.normal(size=data.num_rows))[:, None]
    noise = fit_noise(resid, data)
    assert noise.sigma[0] == pytest.approx(2.0, rel=0.15)
    assert noise.order[0] == 0 and not quantised(data, noise.sigma)
    rounded = data.drop_sensors({})
    object.__setattr__(rounded, "x", np.round(data.x / 20.0) * 20.0)
    assert "quantised" in quantised(rounded, noise.sigma)["T30"]


def test_log10_chi2_tail_matches_scipy_and_stays_finite():
    for x, df in ((3.0, 1), (50.0, 4), (400.0, 10)):
        assert log10_chi2_sf(x, df) == pytest.approx(sps.chi2.logsf(x, df) / np.log(10))
    far = log10_chi2_sf(1e6, 3)
    assert np.isfinite(far) and far < -1e5


def test_prepare_data_counts_the_rows_it_drops_for_nan():
    rng = np.random.default_rng(5)
    rec = _record(rng)
    x, w = rec.x.copy(), rec.w.copy()
    x[[2, 5], rec.x_names.index("T30")] = np.nan
    w[5, 0] = np.inf
    w[9, 1] = np.nan
    # as if the reader had dropped 4 rows of T30 already
    rec = dataclasses.replace(rec, x=x, w=w, dropped={"T30": 4}, dropped_rows=4)
    data = prepare_data(rec, knots=4, candidate_knots=2)
    assert data.num_rows == 57 and np.isfinite(data.x).all()
    assert data.dropped == {"T30": 6, "alt": 1, "Mach": 1}
    assert data.dropped_rows == 7


def test_the_fit_box_widens_a_quantity_of_one_sign_on_the_log_scale():
    """A resistance or a capacity (bounds of one sign) may leave its declared range
    far away from zero (x4 for a bound ratio of 4) but only halve toward zero; a
    quantity that may change sign gets half its range on each side."""
    from jaxcal.diagnosis.fitting.joint import fit_box

    thermal = load("thermal")  # R_sa (0.01, 0.03), R_cs (0.005, 0.02), C_core (1e5,4e5)
    low, high = fit_box(thermal)
    j = thermal.parameter_names.index("R_cs")
    np.testing.assert_allclose([low[j], high[j]], [0.0025, 0.08])
    j = thermal.parameter_names.index("C_core")
    np.testing.assert_allclose([low[j], high[j]], [5e4, 1.6e6])
    j = thermal.parameter_names.index("R_sa")  # additive would reach 0: sqrt(3) kept
    np.testing.assert_allclose([low[j], high[j]], [0.01 / np.sqrt(3.0), 0.09])
    assert np.all(low[: len(thermal.parameters)] > 0)
    hx = load("heat_exchanger")  # fouling (0, 0.6): from zero, additive both ways
    low, high = fit_box(hx)
    j = hx.parameter_names.index("fouling")
    np.testing.assert_allclose([low[j], high[j]], [-0.3, 0.9])
    engine = load("cmapss")  # health modifiers (-0.3, 0.03): across zero, additive
    low, high = fit_box(engine)
    np.testing.assert_allclose([low[0], high[0]], [-0.465, 0.195])
