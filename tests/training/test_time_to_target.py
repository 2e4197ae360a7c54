"""The training job's time to target and its uncertainty band, on the smoke preset.

A loose target is reached at the first scoring, an impossible one never; the time to
target reads the validation units' theta RMSE, reporting only, so both runs keep the
same policy and no test pass runs during training. The kept policy's
band is written to ``uncertainty.json`` and its test coverage to ``final.json``;
a run without validation units has no band. The smoke compilations are shared with
the other pipeline tests through ``make_components``' cache.
"""

import numpy as np
import pytest
from support.synthetic_file import write_synthetic_ncmapss

from jaxcal.calibrators.interface import CalOutput
from jaxcal.calibrators.uncertainty.conformal import UNCERTAINTY_FILE, load_band
from jaxcal.cli.train import format_final
from jaxcal.data.padded import Padded
from jaxcal.runs.metrics_log import read_metrics
from jaxcal.training import pipeline
from jaxcal.training.config import resolve_config
from jaxcal.training.pipeline import run_training
from jaxcal.training.stages import uncertainty as uncertainty_stage
from jaxcal.training.stages.uncertainty import fit_policy_band, time_to_target


@pytest.fixture(scope="module")
def data_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "synthetic.h5"
    return write_synthetic_ncmapss(path, dev_units=(1, 2, 3), test_units=(4, 5))


def _run(data_file, runs_dir, name, *extra):
    cfg = resolve_config(
        [
            "dataset=ncmapss",
            "preset=smoke",
            f"path={data_file}",
            "dataset.stride=1",
            f"output.runs_dir={runs_dir}",
            "output.progress=false",
            f"output.name={name}",
            "budget.num_chunks=3",
            "budget.eval_every=1",
            *extra,
        ]
    )
    notes = []
    final = run_training(cfg, log=notes.append)
    return final, notes


BAND_RUNS = []  # (the validation run kept from the chunk's scoring, a fresh one)


def _spy_band_runs(run, band_units, test, params, made=None):
    BAND_RUNS.append((made, run(band_units, params)))
    return uncertainty_stage.band_runs(run, band_units, test, params, made)


@pytest.fixture(scope="module")
def runs(data_file, tmp_path_factory):
    runs_dir = tmp_path_factory.mktemp("runs")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pipeline, "band_runs", _spy_band_runs)
        loose = _run(data_file, runs_dir, "loose", "budget.target_theta_rmse=1.0")
    never = _run(data_file, runs_dir, "never", "budget.target_theta_rmse=1e-12")
    return runs_dir, loose, never


def test_a_reachable_target_is_timed_at_its_first_scoring(runs):
    runs_dir, (final, notes), _ = runs
    assert final["target_theta_rmse"] == 1.0
    assert final["time_to_target_chunk"] == 1
    assert 0 < final["time_to_target_s"] <= final["session_wall_seconds"]
    assert final["target_scorings"] == 3
    records = read_metrics(runs_dir / "loose" / "metrics.jsonl")
    assert all("job_seconds" in r for r in records)
    # the validation units' theta RMSE times it: no test pass during training
    assert not any(k.startswith("test_") for r in records for k in r)
    assert records[0]["val_theta_rmse"] <= 1.0
    assert records[0]["time_to_target_s"] == final["time_to_target_s"]
    assert records[0]["time_to_target_chunk"] == 1
    assert not any("time_to_target_s" in r for r in records[1:])  # first only
    assert any("<= target" in n for n in notes)
    assert "time to target" in format_final(final)


def test_an_unreachable_target_is_null_and_selection_ignores_test_scores(runs):
    _, (loose, _), (never, notes) = runs
    assert never["time_to_target_s"] is None
    assert never["time_to_target_chunk"] is None
    assert never["target_scorings"] == 3
    assert not any("<= target" in n for n in notes)
    assert "not reached in 3 scorings" in format_final(never)
    # the test scores are reporting only: the same policy is kept, scored the same
    assert never["selected_chunk"] == loose["selected_chunk"]
    assert never["test"] == loose["test"]


def test_the_kept_policy_gets_a_band_measured_on_test_units(runs):
    runs_dir, (final, _), _ = runs
    band = load_band(runs_dir / "loose")
    assert band is not None and int(band.edges[0]) == 0
    assert band.std.shape == (len(band.edges), 1)
    assert np.all(np.isfinite(band.std)) and np.all(np.asarray(band.std) > 0)
    meta = final["uncertainty"]
    assert meta["file"] == UNCERTAINTY_FILE and meta["val_units"] == [3]
    assert meta["num_samples"] > 20 and meta["level"] == 0.9
    assert 0.0 <= final["test_coverage90"] <= 1.0
    assert set(final["test_coverage90_per_param"]) == {"HPT_eff_mod"}
    assert "90 % theta band" in format_final(final)


def test_the_band_reuses_the_kept_chunks_validation_run(runs):
    # made once when the kept chunk was scored, not again: the same bits
    ((made, fresh),) = BAND_RUNS
    assert made is not None
    for name in ("theta", "xhat", "valid", "reason"):
        np.testing.assert_array_equal(getattr(made, name), getattr(fresh, name))


def test_no_validation_units_means_no_band_and_a_note(tmp_path):
    # what run_training passes for a run without validation units (val_units=)
    test = Padded(
        w=np.zeros((1, 30, 4)), x=np.zeros((1, 30, 2)), theta=np.zeros((1, 30, 1)),
        lengths=np.array([30]), unit_ids=np.array([4]),
    )  # fmt: skip
    out = CalOutput(theta=np.zeros((1, 30, 1)), xhat=np.zeros((1, 30, 2)))
    notes = []
    fields = fit_policy_band(None, None, test, out, tmp_path, ("a",), log=notes.append)
    assert fields["test_coverage90"] is None and fields["uncertainty"]["file"] is None
    assert not (tmp_path / UNCERTAINTY_FILE).exists()
    assert notes == ["no uncertainty band: no validation units to fit it on"]
    # with validation units the band is written and checked on the test units
    fields = fit_policy_band(test, out, test, out, tmp_path, ("a",), log=notes.append)
    assert fields["test_coverage90"] == 1.0 and load_band(tmp_path) is not None
    # no target: no time; a target: the first validation scoring at or below it
    timing = time_to_target([{"step": 1, "val_theta_rmse": 0.1}], None)
    assert timing["time_to_target_s"] is None and timing["target_scorings"] == 0
    records = [{"step": s, "val_theta_rmse": v, "job_seconds": 10.0 * s}
               for s, v in ((2, 0.3), (1, 0.5), (3, 0.05))]  # fmt: skip
    timing = time_to_target(records, 0.3)
    assert timing["time_to_target_chunk"] == 2 and timing["time_to_target_s"] == 20.0
