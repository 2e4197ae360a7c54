"""Faults that start mid-life, in some units, under coloured noise (issue 24).

The pumps of ``test_units`` (a model defined in the tests, cheap to compile): a
thermometer that steps from mid-life in two of eight units, a leak that jumps (sudden
damage) in three, and clean data with AR(1) noise. The step is named as a step (not a
drift or a bias), fitted in its carriers only, with onsets inside their intervals;
the clean coloured record raises no alarm with the noise model and does without it.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_units import NOISE, PUMP, STEPS, UNITS, pump

from jaxcal.data.dataset import Dataset
from jaxcal.diagnosis.data.synthetic import ar1_noise
from jaxcal.diagnosis.pipeline import LoopConfig, diagnose


def _fleet(seed=0, carriers=(), step=0.0, leak_jump=0.0, onsets=None, phi=0.0):
    rng = np.random.default_rng(seed)
    n = UNITS * STEPS
    w = np.stack(
        [rng.uniform(0.6, 2.0, n), rng.uniform(0.8, 1.2, n), rng.uniform(285, 315, n)],
        axis=1,
    )
    unit = np.repeat(np.arange(1, UNITS + 1), STEPS)
    time = np.tile(np.arange(1, STEPS + 1), UNITS).astype(float)
    onsets = onsets or {u: 20 + 7 * i for i, u in enumerate(carriers)}
    onset_of_row = np.array([onsets.get(u, np.inf) for u in unit])
    after = time >= onset_of_row
    theta = np.zeros((n, 3))
    theta[:, 0] = 0.1 * time / STEPS
    theta[:, 1] = leak_jump * after
    x = np.array(jax.vmap(pump)(jnp.asarray(w), jnp.asarray(theta)))
    x[:, 2] += step * after
    noise = ar1_noise(rng, x.shape, unit, phi)
    x += np.array(list(NOISE.values())) * noise
    data = Dataset(
        w=w, x=x, condition_names=PUMP.condition_names,
        output_names=PUMP.output_names, unit=unit, time=time, theta=theta,
        theta_names=PUMP.parameter_names,
    )  # fmt: skip
    return data, onsets


@pytest.mark.parametrize(
    "kwargs,name",
    [
        ({"carriers": (3, 6), "step": 0.4}, "sensor_step[t_out]"),
        ({"carriers": (2, 5, 7), "leak_jump": 0.03}, "parameter_step[leak]"),
    ],
)
def test_a_step_in_some_units_is_named_with_its_onsets(kwargs, name):
    data, onsets = _fleet(**kwargs)
    res = diagnose(data, PUMP, ["wear"], noise_std=NOISE)
    assert res.added == [name], res.identification.ranking[:3]
    cand, eff = res.members[0], res.unit_effects[0]
    assert cand.form == "units"
    assert (np.flatnonzero(eff.carries) + 1).tolist() == list(kwargs["carriers"])
    for u in kwargs["carriers"]:
        lo, hi = eff.onset_ci[u - 1]
        assert abs(eff.onset[u - 1] - onsets[u]) <= 2, (eff.onset, onsets)
        assert lo - 1 <= onsets[u] <= hi + 1  # the interval holds the truth
    # no unit without the fault is said to carry it, and the clean ones get no size
    assert not eff.carries[[u - 1 for u in range(1, UNITS + 1)
                            if u not in kwargs["carriers"]]].any()  # fmt: skip


def test_coloured_noise_raises_no_alarm_with_the_noise_model():
    """Clean pumps, AR(1) noise with coefficient 0.8, the noise levels estimated.
    Prewhitened, nothing is found; with the white-noise diagnosis of before (the
    same data, noise_order=0) the colour is read as effects."""
    alarms_white, alarms_ar = [], []
    for seed in range(3):
        data, _ = _fleet(seed=10 + seed, phi=0.8)
        ar = diagnose(data, PUMP, ["wear"])
        white = diagnose(data, PUMP, ["wear"], LoopConfig(noise_order=0))
        alarms_ar.append(ar.verdict != "none")
        alarms_white.append(white.verdict != "none")
        assert ar.data.noise.order.min() >= 1  # the colour is seen
        assert np.all(ar.after.whiteness_p > 0.001)  # and whitened away
    assert not any(alarms_ar), alarms_ar
    assert any(alarms_white), alarms_white


def test_one_wild_reading_is_left_out_and_said():
    """A reading of 1e6 in one row of one unit (issue 25): the row is left out as an
    outlier, the report says so, and the clean fleet stays clean."""
    data, _ = _fleet(seed=3)
    x = data.x.copy()
    x[100, 1] = 1e6  # unit 2
    data = data._replace(x=x) if hasattr(data, "_replace") else type(data)(
        **{**data.__dict__, "x": x}
    )  # fmt: skip
    res = diagnose(data, PUMP, ["wear"])
    assert res.verdict == "none", res.added
    note = next(n for n in res.data.notes if "outlier" in n)
    assert "1 outlier row (units 2 (1); outputs power (1)" in note
    assert res.data.num_rows == UNITS * STEPS - 1
    np.testing.assert_allclose(res.data.noise_std, list(NOISE.values()), rtol=0.25)


def test_the_noise_is_refitted_to_the_rival_that_leaves_the_least_residual():
    """Once a winner stands, the noise model's basis is the fit of the winner or of
    a single effect within the BIC margin of it, whichever has the larger likelihood
    ratio (pipeline._winner_basis): a winner's misfit read as noise kept a step from
    separating from the drift that won. A pair, or a single beyond the margin, is
    never the basis."""
    from types import SimpleNamespace

    from jaxcal.diagnosis.fitting.identify import Identification
    from jaxcal.diagnosis.pipeline import _winner_basis

    def entry(name, bic, lr, members=1):
        return SimpleNamespace(name=name, bic=bic, lr_stat=lr, members=(0,) * members)

    won = entry("sensor_gain_drift[p]", 100.0, 50.0)
    rival = entry("parameter_step[c]", 100.7, 56.5)
    far = entry("sensor_step[p]", 111.0, 80.0)
    pair = entry("sensor_gain_drift[p] + parameter_step[c]", 98.0, 90.0, members=2)
    fits = {e.name: f"fit of {e.name}" for e in (won, rival, far, pair)}

    def ident(ranking, winner):
        return Identification(None, ranking, winner, fits[winner.name], [], [], 4,
                              fits, {})  # fmt: skip

    assert _winner_basis(ident([pair, won, rival, far], won), 10.0) == fits[rival.name]
    assert _winner_basis(ident([pair, won, rival, far], won), 0.5) == fits[won.name]
    # a pair that won keeps its own fit: a rival single explains less
    assert _winner_basis(ident([pair, won, rival], pair), 10.0) == fits[pair.name]
