"""An effect carried by some units only is added for those units (issue 43 item 3).

A toy heater fleet of 6 units, a +1.5 K step of the outlet thermometer from row 30 in
units 1 and 3. The extended model with the offset for the carriers only calibrates
the clean units as the base model does (the offset held at 0, std 0) and tracks the
carriers' step; the same extension for every unit (what the export did before) costs
the clean units accuracy. Plus the file format: ``units`` per added parameter, old
files (no ``units``) read as every unit, a malformed one named.
"""

import json
import types
import warnings

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import jaxcal
from jaxcal.calibrators.front.carriers import unit_groups
from jaxcal.diagnosis.kinds.table import build_library
from jaxcal.diagnosis.report.extended import added_parameters, extension_json
from jaxcal.diagnosis.report.units import UnitEffect
from jaxcal.models import load_extended
from jaxcal.models.extended import Added, build_extended

UNITS, ROWS, ONSET, STEP = 6, 100, 30, 1.5
CARRIERS = (1, 3)
NOISE = {"T_out": 0.05, "P": 0.05}


def heater(w, theta):
    """``(T_out K, P kW)`` of a heater of conductance ``k`` at duty ``q``."""
    q, t_in = w[0], w[1]
    k, h = theta[0], theta[1]
    return jnp.stack([t_in + q / (k + 0.1 * q), h * q + 2.0 * k])


BASE = jaxcal.Model.from_function(
    heater,
    conditions={"q": "kW", "T_in": "K"},
    parameters={"k": (1.0, 0.5, 2.0, "kW/K"), "h": (2.0, 1.0, 3.0, "-")},
    outputs={"T_out": "K", "P": "kW"},
    name="heater",
)
DECLARED = ("k", "h")


def _fleet() -> pd.DataFrame:
    """The fleet: ``k`` fouling along each record, the step in the carriers."""
    rng = np.random.default_rng(0)
    parts = []
    for u in range(UNITS):
        t = np.arange(ROWS)
        q, t_in = rng.uniform(1, 5, ROWS), rng.uniform(280, 300, ROWS)
        k, h = 1.0 + 0.03 * u + 0.3 * t / ROWS, np.full(ROWS, 2.0 + 0.1 * u)
        x = np.stack([t_in + q / (k + 0.1 * q), h * q + 2.0 * k], axis=1)
        x = x + [NOISE["T_out"], NOISE["P"]] * rng.normal(size=x.shape)
        x[:, 0] += STEP * (t >= ONSET) * (u in CARRIERS)
        parts.append(pd.DataFrame({
            "unit": u, "time": t, "q": q, "T_in": t_in, "T_out": x[:, 0],
            "P": x[:, 1], "k": k, "h": h,
        }))  # fmt: skip
    return pd.concat(parts, ignore_index=True)


def _offset(units) -> Added:
    return Added("T_out_offset", "additive", "T_out", 0.0, -5.0, 5.0, "K", 0.05, units)


def _declared_error(res, data: pd.DataFrame) -> np.ndarray:
    """``[U]`` RMSE of the declared parameters over each unit's rows from the onset
    on, in units of their box half-width (one number per unit)."""
    out = np.zeros(UNITS)
    for u in range(UNITS):
        rows = (res.unit == u) & (res.time >= ONSET)
        errs = [
            (res.theta[rows, res.theta_names.index(p)] - data[p].to_numpy()[rows])
            / (BASE.parameters[j].high - BASE.parameters[j].low)
            for j, p in enumerate(DECLARED)
        ]
        out[u] = np.sqrt(np.mean(np.square(errs)))
    return out


def _calibrate(model, data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the carriers' misfit note
        return jaxcal.calibrate(model, data, "ukf", noise=NOISE, progress=False, **kw)


def test_clean_units_calibrate_as_with_the_base_model_and_carriers_track_it():
    data = _fleet()
    base = _calibrate(BASE, data, theta=list(DECLARED))
    per_unit = build_extended(BASE, DECLARED, [_offset(CARRIERS)])
    every = build_extended(BASE, DECLARED, [_offset(None)])
    assert per_unit.diagnosis.carriers == {"T_out_offset": CARRIERS}
    res = _calibrate(per_unit, data, misfit="keep")  # a step: the filter lags it
    res_every = _calibrate(every, data, misfit="keep")
    assert res.theta_names == ("k", "h", "T_out_offset")
    assert any("held at nominal in unit(s) [0, 2, 4, 5]" in n for n in res.notes)

    clean = np.setdiff1d(np.arange(UNITS), CARRIERS)
    err_base, err = _declared_error(base, data), _declared_error(res, data)
    err_every = _declared_error(res_every, data)
    assert np.all(err[clean] <= 1.05 * err_base[clean] + 1e-4), (err, err_base)
    # the extension tracked everywhere does worse on the clean units: the fix matters
    assert err_every[clean].mean() > 1.5 * err_base[clean].mean(), err_every
    # ... and better than the base model on the carriers, whose step it absorbs
    assert np.all(err[list(CARRIERS)] < err_base[list(CARRIERS)])

    j = res.theta_names.index("T_out_offset")
    held = np.isin(res.unit, clean)
    assert np.all(res.theta[held, j] == 0.0) and np.all(res.theta_std[held, j] == 0.0)
    for u in CARRIERS:
        last = np.flatnonzero(res.unit == u)[-1]
        est, std = res.theta[last, j], res.theta_std[last, j]
        assert 0.0 < std < 0.2 and abs(est - STEP) <= 2.0 * std, (u, est, std)


def test_a_parameter_every_unit_carries_is_no_split():
    data = _fleet().query("unit in @CARRIERS")
    model = build_extended(BASE, DECLARED, [_offset(CARRIERS)])
    res = _calibrate(model, data)
    assert not any("held at nominal" in n for n in res.notes)
    assert unit_groups(model, ("k", "T_out_offset"), np.array([0, 1])) == [
        ((0,), ("k",)),
        ((1,), ("k", "T_out_offset")),
    ]
    with pytest.raises(ValueError, match=r"unit\(s\) \[0\] carry none"):
        unit_groups(model, ("T_out_offset",), np.array([0, 1]))


def test_the_file_keeps_the_carriers_and_reads_an_old_one_as_every_unit(tmp_path):
    spec = {
        "format": "jaxcal.extended_model/1", "base": "heat_exchanger",
        "declared": ["fouling"], "added": [{
            "name": "T_hot_out_offset", "channel": "additive", "target": "T_hot_out",
            "nominal": 0.0, "low": -5.0, "high": 5.0, "unit": "K", "scale": 0.05,
        }],
    }  # fmt: skip
    path = tmp_path / "extended_model.json"
    path.write_text(json.dumps(spec))
    assert load_extended(str(path)).diagnosis.carriers is None  # an older file
    spec["added"][0]["units"] = [3, 1]
    path.write_text(json.dumps(spec))
    loaded = load_extended(str(path))
    assert loaded.diagnosis.carriers == {"T_hot_out_offset": (1, 3)}
    spec["added"][0]["units"] = "1,3"
    path.write_text(json.dumps(spec))
    with pytest.raises(ValueError, match=r"extended_model.json.*'units' must be"):
        load_extended(str(path))


def test_the_diagnosis_adds_a_per_unit_effect_for_its_carriers():
    lib = build_library(BASE, DECLARED, ("T_out", "P"), np.ones(2), np.ones(2))
    by_name = {c.name: c for c in lib}
    step = by_name["sensor_step[T_out]"].with_form("units", [1, 3], [30, 130])
    bias = by_name["sensor_bias[P]"]  # fleet-wide: every unit

    def effect(carries):
        nan = np.full(4, np.nan)
        return UnitEffect("e", "units", np.ones(4), np.ones(4), np.ones(4),
                          np.asarray(carries), nan, np.full((4, 2), np.nan), 0.1,
                          np.zeros(8), np.zeros(4), np.zeros(4))  # fmt: skip

    data = types.SimpleNamespace(unit_ids=np.array([10, 11, 12, 13]), tau=np.ones(8))
    res = types.SimpleNamespace(
        model=BASE,
        declared=DECLARED,
        data=data,
        members=(step, bias),
        unit_effects=(effect([False, True, False, False]), effect([True] * 4)),
    )
    added = {a.name: a.units for a in added_parameters(res)}
    assert added == {"T_out_offset": (11,), "P_offset": None}  # the verdict's
    res.unit_effects = (effect([False] * 4), res.unit_effects[1])
    assert added_parameters(res)[0].units == (11, 13)  # none passed: the screen's
    spec = extension_json(res, "heater")
    assert [a["units"] for a in spec["added"]] == [[11, 13], None]


def test_any_registered_filter_calibrates_the_exported_model_by_carriers():
    """The EKF (a method the diagnosis never names) splits an extended model's units
    by their carriers as the UKF does, and tracks the carriers' offset."""
    data = _fleet()
    per_unit = build_extended(BASE, DECLARED, [_offset(CARRIERS)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        res = jaxcal.calibrate(
            per_unit, data, "ekf", noise=NOISE, progress=False, misfit="keep"
        )
    assert res.method == "ekf"
    assert any("held at nominal in unit(s) [0, 2, 4, 5]" in n for n in res.notes)
    j = res.theta_names.index("T_out_offset")
    clean = np.setdiff1d(np.arange(UNITS), CARRIERS)
    assert np.all(res.theta[np.isin(res.unit, clean), j] == 0.0)
    for u in CARRIERS:
        last = np.flatnonzero(res.unit == u)[-1]
        assert abs(res.theta[last, j] - STEP) <= 2.0 * res.theta_std[last, j]
