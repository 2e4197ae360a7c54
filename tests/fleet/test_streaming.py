"""Streaming fleet calibration: chunked == one-shot, one compiled program, atomic
output, and N-CMAPSS chunks that match a whole-file load."""

import os

import jax
import numpy as np
import pytest
from fleet_worker import problem, reference, ukf

from jaxcal.calibrators.interface import REASON_CODE, Calibrator, SampleCheck
from jaxcal.fleet.results import FleetResultWriter, read_results
from jaxcal.fleet.sharded import make_unit_mesh
from jaxcal.fleet.streaming import (
    UnitChunk,
    calibrate_stream,
    iter_array_chunks,
    plan_chunks,
    units_per_chunk,
)
from jaxcal.models.turbofan.data.ncmapss_io import load_ncmapss, write_ncmapss
from jaxcal.models.turbofan.data.record import Record
from jaxcal.models.turbofan.fleet import iter_ncmapss_chunks, sensor_norm, unit_lengths
from jaxcal.models.turbofan.physics.constants import (
    MEASURED_SENSOR_NAMES,
    VIRTUAL_SENSOR_NAMES,
)

NAMES = dict(theta_names=("a", "b"), sensor_names=("s0", "s1", "s2"))


def counting(calibrator: Calibrator, counter: list) -> Calibrator:
    """The same calibrator, counting how often ``init`` is traced."""

    def init(key, w0, x0):
        counter.append(1)
        return calibrator.init(key, w0, x0)

    return Calibrator(init=init, step=calibrator.step)


@pytest.fixture(scope="module")
def counted_ukf():
    """One counting UKF shared by the stream tests (chunks of 2 units: one program)."""
    w, x, mask, theta, measure = problem(num_units=5)
    traces = []
    return counting(ukf(measure), traces), traces


def test_plan_chunks_covers_units_in_order():
    plan = plan_chunks(7, 3, num_processes=2)
    assert [[p.tolist() for p in parts] for parts in plan] == [
        [[0, 1], [2]],
        [[3, 4], [5]],
        [[6], []],
    ]
    with pytest.raises(ValueError, match="chunk_units"):
        plan_chunks(5, 0)


def test_chunked_stream_equals_one_shot_and_compiles_once(tmp_path, counted_ukf):
    w, x, mask, theta, measure = problem(num_units=5)
    calibrator, traces = counted_ukf
    ref = reference(ukf(measure), w, x, mask)
    mesh = make_unit_mesh([jax.devices()[0]])
    path = tmp_path / "out.h5"
    unit_ids = 10 + np.arange(5)
    chunks = iter_array_chunks(
        w, x, mask, 2, unit_ids=unit_ids, extras={"theta_true": theta}
    )
    with FleetResultWriter(path, attrs={"method": "ukf"}, **NAMES) as writer:
        stats = calibrate_stream(
            calibrator, chunks, mesh, size=units_per_chunk(2, 1, mesh), writer=writer
        )
    # 3 chunks (2 + 2 + 1 units) and the failure test's chunk: one compiled program.
    assert len(traces) == 1
    assert stats["num_chunks"] == 3 and stats["num_units"] == 5
    assert stats["num_rows"] == int(mask.sum())
    arrays, attrs = read_results(path)
    assert attrs["method"] == "ukf" and attrs["theta_names"] == ["a", "b"]
    np.testing.assert_allclose(arrays["theta"], ref.theta[mask], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(arrays["xhat"], ref.xhat[mask], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(
        arrays["aux_theta_std"], ref.aux["theta_std"][mask], rtol=1e-12, atol=1e-14
    )
    np.testing.assert_array_equal(arrays["theta_true"], theta[mask])
    np.testing.assert_array_equal(arrays["unit"], np.repeat(unit_ids, mask.sum(1)))
    np.testing.assert_array_equal(arrays["step"], np.nonzero(mask)[1])
    np.testing.assert_array_equal(arrays["unit_id"], unit_ids)
    np.testing.assert_array_equal(arrays["unit_length"], mask.sum(1))
    last = ref.theta[np.arange(5), mask.sum(1) - 1]
    np.testing.assert_allclose(arrays["unit_theta_last"], last, rtol=1e-12)


def test_failed_stream_leaves_no_file_and_keeps_the_old_one(tmp_path, counted_ukf):
    w, x, mask, _, _ = problem(num_units=5)
    path = tmp_path / "out.h5"
    path.write_bytes(b"previous results")

    def broken_chunks():
        yield from iter_array_chunks(w[:1], x[:1], mask[:1], 1)
        raise OSError("disk went away")

    with pytest.raises(OSError, match="disk went away"):
        with FleetResultWriter(path, **NAMES) as writer:
            calibrate_stream(
                counted_ukf[0],
                broken_chunks(),
                make_unit_mesh([jax.devices()[0]]),
                size=2,
                writer=writer,
            )
    assert path.read_bytes() == b"previous results"
    assert os.listdir(tmp_path) == ["out.h5"]  # the temporary file is gone


def test_stream_rejects_oversized_chunks(tmp_path):
    w, x, mask, _, measure = problem(num_units=5)
    chunk = UnitChunk(np.arange(3), np.arange(3), w[:3], x[:3], mask[:3])
    with pytest.raises(ValueError, match="need 1 .. size=2"):
        calibrate_stream(ukf(measure), [chunk], make_unit_mesh(), size=2)
    with pytest.raises(ValueError, match="empty"):
        calibrate_stream(ukf(measure), [], make_unit_mesh(), size=2)


def test_stream_skips_and_flags_poisoned_samples(tmp_path):
    """Issue 12: a NaN or out-of-range sample is skipped, flagged in the file (valid,
    reason columns) and counted in the summary; other samples are untouched."""
    w, x, mask, _, measure = problem(num_units=3)
    check = SampleCheck.from_range(
        w[mask].min(0), w[mask].max(0), x[mask].min(0), x[mask].max(0), margin=0.5
    )
    w, x = w.copy(), x.copy()
    x[1, 2, 0] = np.inf  # (a NaN in one output is a partial row, used by the UKF)
    w[2, 3, 0] = 1e6
    calibrator = ukf(measure)
    path = tmp_path / "flags.h5"
    mesh = make_unit_mesh([jax.devices()[0]])
    with FleetResultWriter(path, **NAMES) as writer:
        stats = calibrate_stream(
            calibrator, iter_array_chunks(w, x, mask, 2), mesh,
            size=units_per_chunk(2, 1, mesh), writer=writer, check=check,
        )  # fmt: skip
    assert stats["num_flagged"] == 2
    assert stats["flagged"]["x_nonfinite"] == 1
    assert stats["flagged"]["w_out_of_range"] == 1
    arrays, attrs = read_results(path)
    assert attrs["flagged"]["x_nonfinite"] == 1 and attrs["reasons"][0] == "ok"
    assert np.isfinite(arrays["theta"]).all()
    row = np.flatnonzero((arrays["unit"] == 1) & (arrays["step"] == 2))[0]
    assert not arrays["valid"][row]
    assert arrays["reason"][row] == REASON_CODE["x_nonfinite"]
    np.testing.assert_array_equal(arrays["theta"][row], arrays["theta"][row - 1])
    assert arrays["valid"].sum() == mask.sum() - 2
    # unit 0 saw no bad sample: the same as the unguarded reference
    ref = reference(calibrator, w, x, mask)
    n0 = int(mask[0].sum())
    np.testing.assert_allclose(arrays["theta"][:n0], ref.theta[0][mask[0]], rtol=1e-12)


def test_stream_uses_partial_rows_and_marks_them(tmp_path):
    """Issue 25: a row with some outputs missing is used by the UKF (on the observed
    ones), marked in the file's ``partial`` column and counted, and the results are
    those of ``run_fleet`` on the same rows."""
    w, x, mask, _, measure = problem(num_units=3)
    x = x.copy()
    x[0, 1, 2] = np.nan
    x[2, 3, :2] = np.nan
    calibrator = ukf(measure)
    path = tmp_path / "partial.h5"
    mesh = make_unit_mesh([jax.devices()[0]])
    with FleetResultWriter(path, **NAMES) as writer:
        stats = calibrate_stream(
            calibrator, iter_array_chunks(w, x, mask, 2), mesh,
            size=units_per_chunk(2, 1, mesh), writer=writer,
        )  # fmt: skip
    assert stats["num_partial"] == 2 and stats["num_flagged"] == 0
    arrays, attrs = read_results(path)
    assert attrs["num_partial"] == 2 and arrays["valid"].all()
    row = np.flatnonzero((arrays["unit"] == 2) & (arrays["step"] == 3))[0]
    assert arrays["partial"][row] and arrays["partial"].sum() == 2
    ref = reference(calibrator, w, x, mask)
    assert np.isfinite(ref.theta).all()
    np.testing.assert_allclose(arrays["theta"], ref.theta[mask], rtol=1e-12)
    # the row moved the estimate (used), unlike a skipped one
    assert not np.array_equal(arrays["theta"][row], arrays["theta"][row - 1])


def make_record(units, lengths, seed) -> Record:
    rng = np.random.default_rng(seed)
    unit = np.concatenate([np.full(n, u) for u, n in zip(units, lengths, strict=True)])
    n = unit.size
    cycle = np.concatenate([1 + np.arange(k) // 4 for k in lengths])
    return Record(
        w=rng.normal(size=(n, 4)) + [2e4, 0.5, 60, 480],
        x=rng.normal(size=(n, 28)) * 10 + 500,
        x_names=MEASURED_SENSOR_NAMES + VIRTUAL_SENSOR_NAMES,
        theta=rng.normal(size=(n, 10)) * 1e-3,
        unit=unit,
        cycle=cycle,
        flight_class=np.ones(n),
        hs=np.ones(n),
        rul=np.zeros(n, int),
    )


@pytest.fixture
def ncmapss_file(tmp_path):
    path = tmp_path / "tiny.h5"
    dev = make_record([1, 2], [4, 5], seed=0)
    test = make_record([3, 5, 6], [7, 3, 9], seed=1)
    write_ncmapss(path, dev, test)
    return path


def test_unit_lengths_with_stride(ncmapss_file):
    ids, lengths = unit_lengths(ncmapss_file, "test", block_rows=4)
    np.testing.assert_array_equal(ids, [3, 5, 6])
    np.testing.assert_array_equal(lengths, [7, 3, 9])
    # Rows 0, 2, 4, ... of the split: unit 3 holds rows 0-6, 5 rows 7-9, 6 rows 10-18.
    ids, lengths = unit_lengths(ncmapss_file, "test", [6, 5], stride=2, block_rows=3)
    np.testing.assert_array_equal(ids, [5, 6])
    np.testing.assert_array_equal(lengths, [1, 5])
    with pytest.raises(ValueError, match="no unit"):
        unit_lengths(ncmapss_file, "test", [4])


def test_ncmapss_chunks_match_whole_file_load(ncmapss_file):
    sensors = ["T30", "Nf", "W21"]
    ids, lengths = unit_lengths(ncmapss_file, "test")
    whole = load_ncmapss(ncmapss_file, "test", sensors=sensors).padded(max_len=10)
    chunks = list(
        iter_ncmapss_chunks(
            ncmapss_file, "test", ids, max_len=10, chunk_units=2, sensors=sensors,
            theta_names=["HPT_eff_mod"],
        )
    )  # fmt: skip
    assert [c.index.tolist() for c in chunks] == [[0, 1], [2]]
    for name in ("w", "x", "mask", "cycle"):
        got = np.concatenate([getattr(c, name) for c in chunks])
        np.testing.assert_array_equal(got, np.asarray(getattr(whole, name)), name)
    truth = np.concatenate([c.extras["theta_true"] for c in chunks])
    np.testing.assert_array_equal(truth[..., 0], np.asarray(whole.theta)[..., 6])
    # Process 1 of 2 gets unit 5 in chunk 0 and, in chunk 1, a dummy copy of unit 6.
    mine = list(
        iter_ncmapss_chunks(
            ncmapss_file, "test", ids, max_len=10, chunk_units=2, sensors=sensors,
            process_index=1, num_processes=2,
        )
    )  # fmt: skip
    assert [c.index.tolist() for c in mine] == [[1], [-1]]
    assert [c.unit_ids.tolist() for c in mine] == [[5], [6]]
    with pytest.raises(ValueError, match="max_len=8 is shorter"):
        list(
            iter_ncmapss_chunks(
                ncmapss_file, "test", ids, max_len=8, chunk_units=3, sensors=sensors
            )
        )


def test_sensor_norm_from_a_data_pass(ncmapss_file):
    sensors = ["T30", "Nf"]
    stats, source = sensor_norm(ncmapss_file, "test", sensors, [3, 6], block_rows=4)
    mean, std = stats
    assert source == "data pass"
    rec = load_ncmapss(ncmapss_file, "test", units=[3, 6], sensors=["T30", "Nf"])
    np.testing.assert_allclose(mean, rec.x.mean(0), rtol=1e-12)
    np.testing.assert_allclose(std, rec.x.std(0), rtol=1e-9)
