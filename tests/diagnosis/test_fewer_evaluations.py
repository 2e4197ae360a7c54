"""Fewer fleet evaluations per fit (issue 43): what each saved evaluation relies on.

A fit stops when the linear model promises less than the stopping gain, without
evaluating that step.
"""

import numpy as np
import pytest
from conftest import DECLARED

import jaxcal.diagnosis.linearization as linearization
from jaxcal.diagnosis.fitting import fit_model
from jaxcal.diagnosis.kinds import build_library
from jaxcal.diagnosis.prepare import prepare_data
from jaxcal.diagnosis.screen import spec_for


@pytest.fixture
def case(engine, synthetic):
    """``(data, null, cand)``: a sensor bias record, its declared-only fit, and the
    true effect as a fleet-wide candidate."""
    syn = synthetic("sensor_bias", 0, "Ps30")
    data = prepare_data(syn.data, engine, noise_std=syn.noise_std)
    null = fit_model(engine, data, spec_for(DECLARED, []))
    library = build_library(
        engine, DECLARED, data.sensor_names, data.noise_std,
        np.abs(data.x).mean(0), np.ones(data.w.shape[1]),
    )  # fmt: skip
    cand = next(c for c in library if c.name == "sensor_bias[Ps30]")
    return data, null, cand


@pytest.fixture
def evaluations(monkeypatch):
    """The row counts the model is evaluated at (cache emptied)."""
    calls = []
    original = linearization.linearize

    def counted(model, w, *args, **kwargs):
        calls.append(w.shape[0])
        return original(model, w, *args, **kwargs)

    monkeypatch.setattr(linearization, "linearize", counted)
    monkeypatch.setattr(linearization, "_LINEARIZED", type(linearization._LINEARIZED)())
    return calls


def test_a_fit_at_its_optimum_stops_without_a_trial(engine, case, evaluations):
    data, _, cand = case
    spec = spec_for(DECLARED, [cand])
    fit = fit_model(engine, data, spec)
    assert fit.converged
    linearization._LINEARIZED.clear()
    evaluations.clear()
    again = fit_model(engine, data, spec, fit.params)
    # the start point only (its model point dropped from the cache just above): a
    # trial whose predicted gain is below the stop would have been a second
    assert len(evaluations) == 1
    assert again.converged and again.iterations == 0
    np.testing.assert_array_equal(again.params.global_coef, fit.params.global_coef)
