"""A transient is not an outlier (issue 43 item 4).

The newcomer's reactor (``tests/support/reactor.py``: a CSTR with two hidden states,
set-point changes every 10-40 samples) with AR(1) noise of coefficient 0.8, three
units of 500 samples, the noise estimated. The diagnosis's first fit is weighted by
the provisional reference noise (1 % of the mean ``|x|``: 3.5 K for a 0.25 K
thermometer), its heat transfer comes out well off, and the residual peaks at each
set-point change; the screening judged by its neighbours alone left out the peaks
(2 rows of this fleet), rows the true parameters explain. Now no row is left out,
and 10-sigma spikes in 0.5 % of the rows are all found, and nothing else.
"""

import numpy as np
import pytest

from jaxcal.calibrators.front.outliers import robust_scale
from jaxcal.data.dataset import Dataset
from jaxcal.diagnosis.data.cleaning import drop_outliers
from jaxcal.diagnosis.data.prepare import prepare_data
from jaxcal.diagnosis.fitting.joint import fit_model
from jaxcal.diagnosis.kinds.terms import ModelSpec
from jaxcal.diagnosis.pipeline import LoopConfig
from tests.support.reactor import MODEL, NOISE, reactor, small_fleet

DECLARED = ("activity", "UA", "dH")
UNITS, ROWS, PHI = 3, 500, 0.8
CFG = LoopConfig()
AROUND = 3  # rows on each side of a set-point change that its transient covers


def _screened(fleet):
    """``(flagged [N] bool, data before the screening)`` of the diagnosis's outlier
    screening on ``fleet`` (the noise estimated, as a new user would run it)."""
    ds = Dataset(
        w=fleet[list(reactor.CONDITIONS)].to_numpy(),
        x=fleet[list(reactor.OUTPUTS)].to_numpy(),
        condition_names=list(reactor.CONDITIONS), output_names=list(reactor.OUTPUTS),
        unit=fleet["unit"].to_numpy(), time=fleet["time"].to_numpy().astype(float),
    )  # fmt: skip
    data = prepare_data(ds, MODEL, knots=CFG.knots, candidate_knots=CFG.candidate_knots)
    spec0 = ModelSpec(DECLARED, initial_state=True)
    null = fit_model(MODEL, data, spec0, max_iters=CFG.max_iters)
    screened, _ = drop_outliers(MODEL, data, spec0, null, CFG)
    # a model with memory keeps a left-out row in time, unobserved
    return data.observed.any(1) & ~screened.observed.any(1), data


def _near_change(fleet) -> np.ndarray:
    """``[N]`` rows within :data:`AROUND` of a set-point change in their unit."""
    w = fleet[list(reactor.CONDITIONS)].to_numpy()
    same_unit = np.r_[
        False, fleet["unit"].to_numpy()[1:] == fleet["unit"].to_numpy()[:-1]
    ]
    change = np.flatnonzero(same_unit & np.r_[False, np.any(np.diff(w, axis=0), 1)])
    near = np.zeros(len(w), bool)
    for k in range(-AROUND, AROUND + 1):
        near[np.clip(change + k, 0, len(w) - 1)] = True
    return near


@pytest.fixture(scope="module")
def clean():
    fleet = small_fleet(0, units=UNITS, rows=ROWS, phi=PHI)
    return fleet, *_screened(fleet)


def test_set_point_transients_are_not_left_out(clean):
    fleet, flagged, _ = clean
    near = _near_change(fleet)
    assert near.sum() > 100  # the fleet has its set-point changes
    assert flagged.mean() <= 0.01
    assert not flagged[near].any(), np.flatnonzero(flagged)


def test_the_same_test_at_the_true_parameters_flags_nothing(clean):
    """The premise: the rows are explained by the true parameters (the residual
    there is the AR(1) noise; none of its departures from the neighbours' median is
    beyond the threshold)."""
    fleet, _, _ = clean
    r = reactor
    truth = np.concatenate([
        np.asarray(r._SIMULATE(g[list(r.CONDITIONS)].to_numpy(),
                               g[list(r.PARAMETERS)].to_numpy()))
        for _, g in fleet.groupby("unit", sort=True)
    ])  # fmt: skip
    resid = fleet[list(r.OUTPUTS)].to_numpy() - truth
    near = np.stack([np.roll(resid, k, axis=0) for k in (-2, -1, 1, 2)], axis=1)
    departure = (resid - np.median(near, axis=1))[2:-2]
    assert np.all(np.abs(departure) / robust_scale(departure) <= CFG.outlier_z)
    np.testing.assert_allclose(resid.std(0), list(NOISE.values()), rtol=0.3)


def test_ten_sigma_spikes_are_still_left_out():
    fleet = small_fleet(0, units=UNITS, rows=ROWS, phi=PHI)
    rng = np.random.default_rng(7)
    n = len(fleet)
    rows = np.sort(rng.choice(n, int(0.005 * n), replace=False))
    outputs = rng.integers(0, 2, rows.size)
    x = fleet[list(reactor.OUTPUTS)].to_numpy().copy()
    sigma = np.array(list(NOISE.values()))
    x[rows, outputs] += rng.choice([-1.0, 1.0], rows.size) * 10.0 * sigma[outputs]
    fleet[list(reactor.OUTPUTS)] = x
    flagged, _ = _screened(fleet)
    assert np.flatnonzero(flagged).tolist() == rows.tolist()
