"""The ``calib-ds1-UKF`` step and its place in the issue's summary.

A toy method reads theta off x (error N(0, SIGMA)) and reports a std 30x too wide:
its raw 90 % interval covers everything, the one rescaled on validation units covers
~90 % of other units, and the estimate is untouched. The summary then shows the
recalibrated coverage and keeps the raw one in ``summary_details``.
"""

import json
import types

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.calibrators.interface import Calibrator, CalStepOutput
from jaxcal.data.padded import Padded
from jaxcal.paper.methods import make_method
from jaxcal.paper.report import write_report
from jaxcal.paper.std_steps import calib_std_step
from jaxcal.paper.summary import GOALS, UKF_CALIB_STEP, issue_summary, summary_json
from jaxcal.paper.tables import Results

SIGMA = np.array([2e-3, 5e-4])
INFLATE = 30.0


def _units(num_units, seed, num_steps=800) -> Padded:
    rng = np.random.default_rng(seed)
    theta = -np.cumsum(rng.uniform(0, 1e-5, (num_units, num_steps, 2)), axis=1)
    x = theta + SIGMA * rng.standard_normal(theta.shape)
    lengths = np.full(num_units, num_steps, np.int32)
    lengths[0] -= 100  # a shorter unit: its padding is not scored
    w = np.tile(np.array([20_000.0, 0.5, 60.0, 500.0]), (num_units, num_steps, 1))
    return Padded(w=w, x=x, theta=theta, lengths=lengths,
                      unit_ids=np.arange(num_units) + 10 * seed)  # fmt: skip


def _toy_method():
    def build(bias, noise_sigma):
        del bias, noise_sigma

        def step(state, w_t, x_t):
            std = jnp.asarray(INFLATE * SIGMA, x_t.dtype)
            return state, CalStepOutput(theta=x_t, xhat=x_t, aux={"theta_std": std})

        return Calibrator(lambda key, w0, x0: jnp.zeros(()), step)

    return make_method("toy", build, jnp.float32, {})


def _suite(val: Padded, test: Padded):
    method = _toy_method()
    return types.SimpleNamespace(
        method=lambda name: method,
        problem=types.SimpleNamespace(theta_names=("a", "b")),
        data=types.SimpleNamespace(val=val),
        cfg=types.SimpleNamespace(max_steps=None),
        test_units=lambda: test,
    )


def test_calib_step_fits_on_validation_and_covers_the_test_units():
    val, test = _units(4, seed=1), _units(6, seed=2)
    out = calib_std_step(_suite(val, test), "toy", seed=0)
    json.dumps(out)  # JSON-ready
    assert out["val_units"] == val.unit_ids.tolist()
    assert out["test_samples"] == int(test.mask.sum())
    assert out["coverage90_raw"] == 1.0
    # ~4,700 test samples: binomial std 0.004, 0.9 +- 0.02 is 5 stds
    assert out["coverage90"] == pytest.approx(0.9, abs=0.02)
    assert out["coverage90_one_scale"] == pytest.approx(0.9, abs=0.02)
    assert out["coverage"]["val"]["buckets"]["coverage90"] >= 0.9
    np.testing.assert_allclose(out["scale_one"]["scale"][0], 1 / INFLATE, rtol=0.1)
    per = out["coverage"]["test"]["buckets"]["coverage90_per_param"]
    assert set(per) == {"a", "b"}
    # the estimate is the method's own: theta = x
    err = (test.x - test.theta)[test.mask]
    assert out["theta_rmse"] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-5)
    raw_median = out["coverage"]["test"]["raw"]["theta_std_median"]
    assert raw_median == pytest.approx(INFLATE * np.median(SIGMA), rel=1e-5)


def test_calib_step_without_validation_units_says_so():
    out = calib_std_step(_suite(None, _units(2, seed=2)), "toy", seed=0)
    assert out["coverage90"] is None and "validation" in out["note"]
    steps = {"eval-ds1-UKF-clean": _ukf_eval(0.9999), UKF_CALIB_STEP: out}
    assert issue_summary(Results(steps))["ds1_ukf_coverage90"] == 0.9999


def _ukf_eval(coverage):
    return {"dataset": "ds1", "variant": "clean", "method": "UKF",
            "theta_rmse": 1e-4, "coverage90": coverage, "units": [7],
            "theta_rmse_per_param": {"a": 1e-4}, "theta_rmse_per_unit": {"7": 1e-4},
            "tracking_rmse_norm": 0.01, "num_samples": 10,
            "batched_samples_per_s": 1.0, "info": {}, "seconds": 1.0,
            "estimate_s": 1.0}  # fmt: skip


def test_summary_shows_the_recalibrated_ukf_coverage_and_keeps_the_raw(tmp_path):
    steps = {"eval-ds1-UKF-clean": _ukf_eval(0.9999)}
    assert issue_summary(Results(steps))["ds1_ukf_coverage90"] == 0.9999
    details = summary_json(Results(steps))["summary_details"]["ds1_ukf_coverage90"]
    assert details["calibrated"] is None and details["raw"] == 0.9999
    steps[UKF_CALIB_STEP] = {"coverage90": 0.91, "coverage90_raw": 0.9999,
                             "coverage90_one_scale": 0.89, "val_units": [6],
                             "scale": {"edges": [0], "scale": [[3e-4]]},
                             "seconds": 1.0, "estimate_s": 1.0}  # fmt: skip
    summary = issue_summary(Results(steps))
    assert set(summary) == set(GOALS)
    assert summary["ds1_ukf_coverage90"] == 0.91
    write_report(
        tmp_path / "REPORT.md", steps, preset="test", description="toy", seed=0,
        command="test", wall_seconds=1.0,
    )  # fmt: skip
    saved = json.loads((tmp_path / "results.json").read_text())
    details = saved["summary_details"]["ds1_ukf_coverage90"]
    assert details["raw"] == 0.9999 and details["calibrated"] == 0.91
    assert saved["summary_goals"]["ds1_ukf_coverage90"]["met"] is True
    text = (tmp_path / "REPORT.md").read_text()
    assert "| `ds1_ukf_coverage90` | 91.0 % |" in text
    assert "the paper's raw std (q = r = 0.01) covers 99.99 %" in text
