"""Data-set builders: file schema, determinism, envelope, noise variants, chunking.

Every build uses the ``tiny`` preset (a few hundred rows, chunk 128) and the shared
jitted engine, so the engine compiles once for the whole module.
"""

import dataclasses
import json

import h5py
import numpy as np
import pytest

from jaxcal.models.turbofan.data.builders import build_dataset
from jaxcal.models.turbofan.data.chunked_engine import (
    RowBlock,
    jit_evaluate_engine,
    solve_rows,
)
from jaxcal.models.turbofan.data.dataset_configs import DATASETS, DatasetConfig
from jaxcal.models.turbofan.data.ncmapss_io import LAYOUT_NAMES, load_ncmapss
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.constants import (
    HEALTH_NAMES,
    MEASURED_SENSOR_NAMES,
    VIRTUAL_SENSOR_NAMES,
)
from jaxcal.settings import config_from_dict

TINY = DATASETS["tiny"]
HPT_EFF = HEALTH_NAMES.index("HPT_eff_mod")


@pytest.fixture(scope="module")
def evaluate():
    """The process-wide jitted engine call (compiled once for chunk_size 128)."""
    return jit_evaluate_engine


@pytest.fixture(scope="module")
def build(tmp_path_factory, evaluate):
    """Build a config into a fresh file; returns the path."""
    directory = tmp_path_factory.mktemp("builds")
    count = iter(range(1000))

    def run(cfg: DatasetConfig):
        path = directory / f"d{next(count)}.h5"
        build_dataset(cfg, path, evaluate=evaluate)
        return path

    return run


@pytest.fixture(scope="module")
def tiny_path(build):
    return build(TINY)


def _arrays(path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f}


def test_file_has_ncmapss_schema(tiny_path):
    with h5py.File(tiny_path, "r") as f:
        groups = ("W", "X_s", "X_v", "T", "Y", "A")
        expected = {f"{g}_{s}" for g in groups for s in ("dev", "test")}
        assert set(f) == expected | {f"{g}_var" for g in LAYOUT_NAMES}
        for split in ("dev", "test"):
            n = f[f"A_{split}"].shape[0]
            assert n > 0
            for group, names in LAYOUT_NAMES.items():
                assert f[f"{group}_{split}"].dtype == np.float64
                assert f[f"{group}_{split}"].shape == (n, len(names))
            assert f[f"Y_{split}"].dtype == np.int64
            assert f[f"Y_{split}"].shape == (n, 1)
        for group, names in LAYOUT_NAMES.items():
            assert f[f"{group}_var"].dtype.kind == "S"
            assert [v.decode() for v in f[f"{group}_var"][()]] == list(names)
        assert f.attrs["sample_rate_hz"] == pytest.approx(1.0 / TINY.dt_s)
        restored = config_from_dict(DatasetConfig, json.loads(f.attrs["config"]))
    assert restored == TINY


def test_rows_are_ordered_by_unit_cycle_time_with_rul_and_hs(tiny_path):
    for split, units in (("dev", TINY.dev_units), ("test", TINY.test_units)):
        rec = load_ncmapss(tiny_path, split)
        assert tuple(rec.units) == tuple(units)
        assert np.all(np.diff(rec.unit) >= 0)
        for u in rec.units:
            sel = rec.unit == u
            cycle, rul, hs = rec.cycle[sel], rec.rul[sel], rec.hs[sel]
            assert np.all(np.diff(cycle) >= 0) and cycle[0] == 1
            np.testing.assert_array_equal(rul, cycle.max() - cycle)
            assert np.all(np.diff(hs) <= 0) and hs[0] == 1 and hs[-1] == 0
            assert np.unique(rec.flight_class[sel]).size == 1


def test_flight_envelope_bounds(tiny_path):
    rec = load_ncmapss(tiny_path, "dev")
    alt, mach, tra, t2 = rec.w.T
    assert alt.min() >= 10_000.0 and alt.max() <= 35_000.0
    assert mach.min() >= 0.2 and mach.max() <= 0.75
    assert tra.min() >= 20.0 and tra.max() <= 100.0
    delta_t = t2 - np.asarray(isa_total_temperature(alt, mach))
    assert np.abs(delta_t).max() <= 25.0 * 1.2  # ISA +- 25 degR static -> total
    assert np.all(np.isfinite(rec.x))


def test_theta_moves_only_in_degrading_parameter(tiny_path):
    rec = load_ncmapss(tiny_path, "dev")
    others = np.delete(rec.theta, HPT_EFF, axis=1)
    np.testing.assert_array_equal(others, 0.0)
    assert rec.theta[:, HPT_EFF].max() <= 0.0
    assert rec.theta[:, HPT_EFF].min() < -0.005


def test_same_seed_is_byte_identical_other_seed_differs(build, tiny_path):
    first, again = _arrays(tiny_path), _arrays(build(TINY))
    assert first.keys() == again.keys()
    for key in first:
        np.testing.assert_array_equal(first[key], again[key], err_msg=key)
    other = _arrays(build(dataclasses.replace(TINY, seed=1)))
    assert not np.array_equal(first["W_dev"][:50], other["W_dev"][:50])


def test_block_size_does_not_change_the_file(build, tiny_path):
    one_shot = _arrays(build(dataclasses.replace(TINY, cycles_per_block=16)))
    chunked = _arrays(tiny_path)  # cycles_per_block=4, several chunks of 128 rows
    for key in chunked:
        np.testing.assert_array_equal(chunked[key], one_shot[key], err_msg=key)


def test_output_bias_scales_every_output(build, tiny_path):
    clean = _arrays(tiny_path)
    biased = _arrays(build(dataclasses.replace(TINY, output_bias=1.02)))
    for group in ("X_s_dev", "X_v_test"):
        np.testing.assert_allclose(biased[group], 1.02 * clean[group], rtol=1e-14)
    np.testing.assert_array_equal(biased["T_dev"], clean["T_dev"])


def test_sensor_noise_hits_measured_sensors_at_the_requested_snr(build, tiny_path):
    clean = _arrays(tiny_path)
    noisy = _arrays(build(dataclasses.replace(TINY, sensor_snr_db=40.0)))
    np.testing.assert_array_equal(noisy["X_v_dev"], clean["X_v_dev"])
    np.testing.assert_array_equal(noisy["W_dev"], clean["W_dev"])
    diff = noisy["X_s_dev"] - clean["X_s_dev"]
    ratio = diff.std(0) / np.sqrt(np.mean(clean["X_s_dev"] ** 2, axis=0))
    assert ratio.shape == (len(MEASURED_SENSOR_NAMES),)
    np.testing.assert_allclose(ratio, 10 ** (-40.0 / 20.0), rtol=0.5)


def test_output_noise_is_sigma_in_normalised_units(build, tiny_path):
    clean = _arrays(tiny_path)
    noisy = _arrays(build(dataclasses.replace(TINY, output_noise_sigma=0.1)))
    with h5py.File(tiny_path, "r") as f:
        names = json.loads(f.attrs["reference_x_names"])
        std = f.attrs["reference_x_std"]
    cols = [names.index(n) for n in VIRTUAL_SENSOR_NAMES]
    z = (noisy["X_v_dev"] - clean["X_v_dev"]) / std[cols]
    assert abs(z.std() - 0.1) < 0.02 and abs(z.mean()) < 0.02


def test_scenario_builder_writes_one_flight_per_scenario(build):
    cfg = dataclasses.replace(TINY, kind="scenarios")
    path = build(cfg)
    dev, test = load_ncmapss(path, "dev"), load_ncmapss(path, "test")
    units = np.concatenate([dev.units, test.units])
    assert sorted(units.tolist()) == list(range(1, cfg.design_size + 1))
    assert not set(dev.units) & set(test.units) and test.units.size == 1
    for rec in (dev, test):
        assert np.all(rec.cycle == 1) and np.all(rec.rul == 0) and np.all(rec.hs == 1)
        counts = np.unique(rec.unit, return_counts=True)[1]
        assert np.all(counts == cfg.flight_steps)
        assert set(np.unique(rec.flight_class)) <= set(range(1, cfg.num_flights + 1))
        np.testing.assert_array_equal(np.delete(rec.theta, HPT_EFF, axis=1), 0.0)
        assert rec.w[:, 0].min() >= 25_700.0 and rec.w[:, 0].max() <= 29_000.0
        assert rec.w[:, 1].min() >= 0.67 and rec.w[:, 1].max() <= 0.74
    levels = np.unique(np.concatenate([dev.theta, test.theta])[:, HPT_EFF])
    np.testing.assert_allclose(np.sort(levels), np.sort(cfg.fault_levels))


def _fake_rows(n: int) -> RowBlock:
    w = np.tile([20_000.0, 0.6, 70.0, 460.0], (n, 1))
    w[:, 0] += 100.0 * np.arange(n)
    ints = np.zeros(n, np.int64)
    return RowBlock(
        w=w, theta=np.zeros((n, 10)), z0=np.zeros((n, 9)), unit=ints + 1,
        cycle=ints + 1, fc=ints + 1, hs=ints + 1, rul=ints, step=np.arange(n),
    )  # fmt: skip


def _fake_engine(converged_fn):
    """Engine stand-in: x = alt, z = 1; ``converged_fn(w, theta, z0)`` -> [B] bool."""

    def evaluate(engine, w, theta, z0):
        del engine
        ok = converged_fn(w, theta, z0)
        return np.repeat(w[:, :1], 35, axis=1), ok, np.ones_like(z0)

    return evaluate


class _Named:
    name = "fake"


def test_non_converged_samples_are_re_solved_from_a_converged_neighbour():
    # odd rows fail from a cold start and converge from any warm start
    evaluate = _fake_engine(
        lambda w, theta, z0: (np.arange(len(w)) % 2 == 0) | (z0 != 0).any(1)
    )
    x, _, retried = solve_rows(
        evaluate, _Named(), _fake_rows(5), chunk_size=8, max_retries=2, where="t"
    )
    assert retried == 2 and x.shape == (5, 35)


def test_remaining_failures_raise_naming_unit_cycle_and_w(tmp_path):
    evaluate = _fake_engine(lambda w, theta, z0: w[:, 0] < 20_250.0)
    with pytest.raises(ValueError, match=r"2 of 5 samples.*unit 1, cycle 1.*w=\{"):
        solve_rows(
            evaluate, _Named(), _fake_rows(5), chunk_size=8, max_retries=1, where="t"
        )
    # the healthy reference pass converges, late-life data chunks do not
    late_life = _fake_engine(lambda w, theta, z0: theta[:, HPT_EFF] > -0.005)
    path = tmp_path / "never.h5"
    with pytest.raises(ValueError, match="did not converge.*dev chunk"):
        build_dataset(TINY, path, evaluate=late_life)
    assert not list(tmp_path.iterdir())  # no file, no temp file left behind


@pytest.mark.parametrize(
    ("field", "value"),
    [("dev_units", (7,)), ("kind", "grid"), ("degrading", ("HPT_eff",)),
     ("dt_s", 0.0), ("num_scenarios", 7), ("sensor_snr_db", float("inf"))],
)  # fmt: skip
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"DatasetConfig.{field}"):
        dataclasses.replace(TINY, **{field: value})


def test_presets_match_the_paper_design():
    cmapss, agtf30 = DATASETS["cmapss"], DATASETS["agtf30"]
    assert [u + 1 for u, c in enumerate(cmapss.unit_classes) if c == 1] == [1, 4, 7, 9]
    assert cmapss.dev_units == (1, 2, 3, 4, 5, 6) and cmapss.test_units == (7, 8, 9, 10)
    assert cmapss.degrading == ("HPT_eff_mod",)
    assert agtf30.design_size == 1296 and len(agtf30.degrading) == 4
    assert agtf30.num_flights * agtf30.flight_steps == 15_000
    assert len(agtf30.observed_sensors) == 8
