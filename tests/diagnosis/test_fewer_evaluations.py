"""Fewer fleet evaluations per fit (issue 43): what each saved evaluation relies on.

A fit stops when the linear model promises less than the stopping gain, without
evaluating that step; a noise pass's refit starts where the last pass's fit of the
same entry ended, its model point kept, so that its first evaluation is free.
"""

import dataclasses

import numpy as np
import pytest
from conftest import DECLARED

import jaxcal.diagnosis.kinds.linearization as linearization
from jaxcal.diagnosis.data.prepare import prepare_data
from jaxcal.diagnosis.fitting.joint import fit_model
from jaxcal.diagnosis.fitting.screen import init_from, spec_for, warm_from
from jaxcal.diagnosis.kinds.table import build_library
from jaxcal.diagnosis.kinds.terms import model_inputs


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


def test_a_fit_at_its_optimum_stops_without_a_trial(engine, case, evaluated_rows):
    data, _, cand = case
    spec = spec_for(DECLARED, [cand])
    fit = fit_model(engine, data, spec)
    assert fit.converged
    linearization._LINEARIZED.clear()
    evaluated_rows.clear()
    again = fit_model(engine, data, spec, fit.params)
    # the start point only (its model point dropped from the cache just above): a
    # trial whose predicted gain is below the stop would have been a second
    assert len(evaluated_rows) == 1
    assert again.converged and again.iterations == 0
    np.testing.assert_array_equal(again.params.global_coef, fit.params.global_coef)


def test_warm_start_takes_the_earlier_fit_of_the_same_entry(engine, case):
    data, null, cand = case
    spec = spec_for(DECLARED, [cand])
    fit = fit_model(engine, data, spec, init_from(null, engine, data, spec))
    same = warm_from(fit, engine, data, spec)
    np.testing.assert_array_equal(same.unit_coef, fit.params.unit_coef)
    np.testing.assert_array_equal(same.global_coef, fit.params.global_coef)
    # a natural step moved with the noise: the same physical size
    rescaled = dataclasses.replace(cand, scale=2.0 * cand.scale)
    moved = warm_from(fit, engine, data, spec_for(DECLARED, [rescaled]))
    np.testing.assert_allclose(moved.global_coef, 0.5 * fit.params.global_coef)
    # another form of the term is no warm start
    units = cand.with_form("units", [0])
    assert warm_from(fit, engine, data, spec_for(DECLARED, [units])) is None


def test_a_remembered_end_point_is_not_evaluated_again(engine, case, evaluated_rows):
    data, null, cand = case
    spec = spec_for(DECLARED, [cand])
    fit = fit_model(engine, data, spec, init_from(null, engine, data, spec))
    linearization._LINEARIZED.clear()
    evaluated_rows.clear()
    inputs = model_inputs(engine, data, fit.layout, fit.params)
    linearization.remember(engine, data, inputs, fit.evaluation.sig.lin)
    again = fit_model(engine, data, spec, warm_from(fit, engine, data, spec))
    assert evaluated_rows == []  # the start served from the kept point, no trial
    assert again.ssr == fit.ssr
