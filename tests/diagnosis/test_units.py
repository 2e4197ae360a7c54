"""The verdict per unit and the plausibility flags (issue 16, parts 1 and 2).

A fleet of small pumps (a model defined here, cheap to compile) where only some units
carry an undeclared effect: the ``units`` list of report.json marks exactly those, with
the keys other tools read. Each plausibility rule is triggered by a constructed case.
"""

import json
import re
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal
from jaxcal.data.dataset import Dataset
from jaxcal.diagnosis.kinds.table import KINDS, Candidate
from jaxcal.diagnosis.pipeline import diagnose
from jaxcal.diagnosis.report.markdown import effect_line, fmt_p, fmt_std
from jaxcal.diagnosis.report.plausibility import degradation_sign, plausibility_flags
from jaxcal.diagnosis.report.units import UnitEffect, UnitTrajectories, holm
from jaxcal.diagnosis.report.write import write_report

UNIT_KEYS = {"unit", "carries", "size", "size_std", "onset", "onset_ci"}


def pump(w, theta):
    """``x [3] = (head m, power kW, t_out K)`` of a centrifugal pump."""
    flow, speed, t_in = w[0], w[1], w[2]
    wear, leak, friction = theta[0], theta[1], theta[2]
    head = 60.0 * speed**2 * (1.0 - wear) - 10.0 * flow**2
    eta = 0.8 * (1.0 - leak)
    power = 9.81 * flow * head / eta + 100.0 * friction * speed**3
    t_out = t_in + 0.05 * power * (1.0 - eta) / flow
    return jnp.stack([head, power, t_out])


PUMP = jaxcal.Model.from_function(
    pump,
    conditions={"flow": "m3/s", "speed": "-", "t_in": "K"},
    parameters={
        "wear": (0.0, 0.0, 0.3, "-"),
        "leak": (0.0, 0.0, 0.3, "-"),
        "friction": (0.0, 0.0, 1.0, "-"),
    },
    outputs={"head": "m", "power": "kW", "t_out": "K"},
    name="pump",
    condition_range=([0.3, 0.7, 270.0], [2.5, 1.3, 340.0]),
)
NOISE = {"head": 0.1, "power": 1.0, "t_out": 0.05}
UNITS, STEPS = 8, 60


def _fleet(carriers, leak_end=0.0, drift=0.0, seed=0):
    """Eight pumps x 60 steps, wear 0 -> 0.1 in all; ``leak`` growing linearly to
    ``leak_end`` and a drift of t_out (K per 100 steps) only in ``carriers``."""
    rng = np.random.default_rng(seed)
    n = UNITS * STEPS
    w = np.stack(
        [rng.uniform(0.6, 2.0, n), rng.uniform(0.8, 1.2, n), rng.uniform(285, 315, n)],
        axis=1,
    )
    unit = np.repeat(np.arange(1, UNITS + 1), STEPS)
    time = np.tile(np.arange(1, STEPS + 1), UNITS).astype(float)
    on = np.isin(unit, carriers)
    theta = np.zeros((n, 3))
    theta[:, 0] = 0.1 * time / STEPS
    theta[:, 1] = on * leak_end * (time - 1) / (STEPS - 1)
    x = np.array(jax.vmap(pump)(jnp.asarray(w), jnp.asarray(theta)))
    x[:, 2] += on * drift * (time - 1) / 100.0
    x += np.array(list(NOISE.values())) * rng.normal(size=x.shape)
    return Dataset(
        w=w, x=x, condition_names=PUMP.condition_names,
        output_names=PUMP.output_names, unit=unit, time=time, theta=theta,
        theta_names=PUMP.parameter_names,
    )  # fmt: skip


@pytest.mark.parametrize(
    "name,carriers,kwargs",
    [
        ("parameter[leak]", [2, 5, 7], {"leak_end": 0.05}),
        ("sensor_drift[t_out]", [2, 3, 4, 5, 6, 7], {"drift": 1.5}),
    ],
)
def test_only_the_carrying_units_are_marked(tmp_path, name, carriers, kwargs):
    res = diagnose(_fleet(carriers, **kwargs), PUMP, ["wear"], noise_std=NOISE)
    assert res.added == [name], res.identification.ranking[:3]
    assert res.flags == ()
    rep = write_report(str(tmp_path), res, source="fleet", model="pump")
    disk = json.loads((tmp_path / "report.json").read_text())
    entry = disk["identified"][0]
    assert all(set(u) == UNIT_KEYS for u in entry["units"])
    assert [u["unit"] for u in entry["units"]] == list(range(1, UNITS + 1))
    # exactly the carriers (no tolerance needed at this signal-to-noise)
    assert [u["unit"] for u in entry["units"] if u["carries"]] == carriers
    truth = kwargs.get("leak_end", kwargs.get("drift"))
    for u in entry["units"]:
        if u["carries"]:
            assert u["onset"] is not None and 1 <= u["onset"] <= STEPS
            # the carriers' sizes within 4 standard errors (or 10 %) of the truth
            tol = max(4 * u["size_std"], 0.1 * truth)
            assert u["size"] == pytest.approx(truth, abs=tol)
        else:
            assert u["onset"] is None and abs(u["size"]) < 4 * u["size_std"]
    k = len(carriers)
    assert entry["carriers"] == k and rep["figures"]["units"] == "units.png"
    assert (tmp_path / "units.png").stat().st_size > 0
    md = (tmp_path / "report.md").read_text()
    assert f"Carried by **{k} of 8 units**" in md
    assert f"{8 - k} units do not carry it" in md and "Holm" in md
    assert not re.search(r"± 0(?![.\d])", md)  # an uncertainty is never printed as 0
    assert not re.search(r"\| 0 \|", md) and not re.search(r"e-3\d\d", md)


def test_a_drift_in_a_few_units_is_fitted_where_it_is():
    """A t_out drift in 3 of 8 units: fitted in those units (the per-unit form, chosen
    by the same criterion as the fleet-wide one), not diluted fleet-wide and
    compensated by a leak in the others (what the fleet-only diagnosis did)."""
    res = diagnose(_fleet([2, 5, 7], drift=1.5), PUMP, ["wear"], noise_std=NOISE)
    assert res.added == ["sensor_drift[t_out]"], res.identification.ranking[:3]
    assert res.members[0].form == "units" and res.flags == ()
    drift = res.unit_effects[0]
    assert (np.flatnonzero(drift.carries) + 1).tolist() == [2, 5, 7]


def test_a_loss_from_the_first_cycle_is_flagged_end_to_end():
    data = _fleet([1, 2, 3, 4, 5, 6, 7, 8], leak_end=0.0)
    data.theta[:, 1] = 0.04  # a leak present, constant, from day one
    x = np.array(jax.vmap(pump)(jnp.asarray(data.w), jnp.asarray(data.theta)))
    rng = np.random.default_rng(1)
    x += np.array(list(NOISE.values())) * rng.normal(size=x.shape)
    data = Dataset(
        w=data.w, x=x, condition_names=data.condition_names,
        output_names=data.output_names, unit=data.unit, time=data.time,
    )  # fmt: skip
    res = diagnose(data, PUMP, ["wear"], noise_std=NOISE)
    assert res.added == ["parameter[leak]"]
    assert "constant_from_start" in {f["flag"] for f in res.flags}


def _fake_data(units=4, rows=10):
    starts = np.arange(0, units * rows + 1, rows)
    return types.SimpleNamespace(
        num_units=units,
        num_rows=units * rows,
        starts=starts,
        unit_ids=np.arange(101, 101 + units),
        sensor_names=("head", "power"),
    )


def _flags(data, after, before=None, effects=(), values=None, rmse=(1.0, 1.0)):
    zeros = {k: np.zeros_like(v) for k, v in after.value.items()}
    before = before or UnitTrajectories(zeros, dict(after.std), {}, {})
    members = [
        Candidate(KINDS["parameter"], "leak", 0.003, "-", "units", (0, 1, 2, 3))
        for _ in effects
    ]
    return plausibility_flags(
        PUMP, data, ("wear",), list(effects), members, values or {}, after, before,
        np.ones(2), np.asarray(rmse), 0.01,
    )  # fmt: skip


def test_each_plausibility_rule_is_triggered_by_a_constructed_case():
    data = _fake_data()
    n = data.num_rows
    std = np.full(n, 1e-4)
    # wear (declared) and leak: "better than new" (negative: the pump's parameters
    # grow with wear, nominal at the lower bound) in the second unit
    value = np.zeros(n)
    value[10:20] = np.linspace(0.0, -0.01, 10)  # improving over the unit's life
    after = UnitTrajectories(
        {"wear": value, "leak": np.zeros(n)}, {"wear": std, "leak": std}, {}, {}
    )
    kinds = {(f["flag"], f["subject"]) for f in _flags(data, after)}
    assert ("better_than_new", "wear") in kinds
    assert ("outside_bounds", "wear") in kinds  # below its lower bound 0
    assert ("declared_against_sign", "wear") in kinds  # moved the wrong way
    flag = next(f for f in _flags(data, after) if f["flag"] == "better_than_new")
    assert flag["units"] == [102]
    # a clean case raises nothing
    clean = UnitTrajectories({"wear": np.full(n, 0.02)}, {"wear": std}, {}, {})
    assert _flags(data, clean) == []
    # an added parameter already at its end value at the first cycle (no change
    # over the record, so no unit carries a developing effect)
    eff = UnitEffect(
        "parameter[leak]", "units", np.zeros(4), np.full(4, 1e-3), np.ones(4),
        np.zeros(4, bool), np.full(4, np.nan), np.full((4, 2), np.nan), 0.0015,
        np.zeros(n), np.array([0.05, 0.05, 0.0, 0.0]), np.full(4, 1e-3),
    )  # fmt: skip
    flags = _flags(data, clean, effects=[eff])
    assert [f["flag"] for f in flags] == ["constant_from_start"]
    assert flags[0]["units"] == [101, 102]
    # a sensor that tracks worse after the extension
    flags = _flags(data, clean, rmse=(1.0, 1.5))
    assert [(f["flag"], f["subject"]) for f in flags] == [("sensor_worse", "power")]


def test_effect_outside_its_stated_range_is_flagged():
    data = _fake_data()
    model = types.SimpleNamespace(
        parameters=PUMP.parameters,
        effects=(jaxcal.Parameter("bleed", 0.0, -0.1, 0.1, "-"),),
        diagnosis=PUMP.diagnosis,
        name="pump+",
    )
    clean = UnitTrajectories({}, {}, {}, {})
    bleed = Candidate(KINDS["effect"], "bleed", 0.002, "-")
    flags = plausibility_flags(
        model, data, ("wear",), [], [bleed], {"bleed": np.array([0.3])}, clean,
        clean, np.ones(2), np.ones(2), 0.01,
    )  # fmt: skip
    assert [(f["flag"], f["subject"]) for f in flags] == [("outside_bounds", "bleed")]


def test_direction_of_wear_defaults_from_the_bounds():
    assert degradation_sign(PUMP, "leak") == 1  # nominal at the lower bound
    from jaxcal.models import load

    hints = load("cmapss").diagnosis.degradation_sign
    assert hints["HPC_eff_mod"] == -1


def test_holm_and_the_printed_numbers():
    p = np.array([0.001, 0.04, 0.0001, 0.5])
    np.testing.assert_array_equal(holm(p, 0.01), [True, False, True, False])
    assert holm(np.array([0.02]), 0.01).tolist() == [False]
    assert fmt_p(0.0) == fmt_p(9.3e-310) == "< 1e-16"
    assert fmt_p(0.0123) == "0.012"
    assert fmt_std(0.0) == fmt_std(float("nan")) == fmt_std(None) == "n/a"
    assert fmt_std(6e-5) == "6e-05"


def test_an_effect_no_unit_carries_says_why():
    """NASA FD002: a per-unit step fitted in 138 units, none past its minimum size."""
    units = [{"size": -0.002}, {"size": None}, {"size": -0.003}]
    e = {"name": "parameter_step[X]", "form": "units", "size": -0.0022,
         "std": 1.3e-4, "unit": "-", "carriers": 0, "min_size": 0.005,
         "units": units}  # fmt: skip
    assert effect_line(e, 3).endswith(
        "(carried by 0 of 3 units: fitted in 2, none beyond its minimum size 0.005)"
    )
    carried = {**e, "carriers": 2}
    assert effect_line(carried, 3).endswith("(carried by 2 of 3 units)")


def test_the_fallback_keeps_a_library_effect_that_explains_better():
    """A t_out bias and a bump in head outside the library: delta(w) on t_out can
    absorb the bias (its constant), and the screen against delta chases what delta
    leaves of the bump; the bias (or its confounded twin, an inlet-temperature offset)
    explains it with one number and is kept beside delta: one BIC, delta's degrees of
    freedom counted, decides between delta alone and either screen's winner."""
    d = _fleet([], seed=2)
    x = d.x.copy()
    x[:, 2] += 0.5
    x[:, 0] += np.exp(-(((d.w[:, 0] - 1.3) / 0.2) ** 2))
    d = Dataset(
        w=d.w, x=x, condition_names=d.condition_names, output_names=d.output_names,
        unit=d.unit, time=d.time,
    )  # fmt: skip
    res = diagnose(d, PUMP, ["wear"], noise_std=NOISE)
    assert res.rescreen is not None
    first = res.identification.winner.name
    assert first in res.added and "discrepancy" in res.added
    assert {first, "sensor_bias[t_out]"} <= {first, *res.confounded}
    assert "kept beside delta" in res.fallback_note
