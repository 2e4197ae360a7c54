"""The front door's noise estimate where one parameter alone explains an output
(``jaxcal/calibrators/front/screen.py``: one-step innovations, corrected for the share
the update absorbs).

The heat exchanger's ``dp_coeff`` moves ``dp_hot`` and nothing else, so the filter
can follow ``dp_hot``'s noise through it: the post-fit residual, the estimate before,
read that noise 60x too small (0.0034 for a true 0.2) and the UKF's ``dp_coeff``
followed the noise (theta RMSE 0.144 against 0.102 with the true noise given).
"""

import sys
from pathlib import Path

import numpy as np
import pytest

import jaxcal

sys.path.insert(
    0, str(Path(__file__).resolve().parents[2] / "examples" / "heat_exchanger")
)
from make_data import NOISE, make_fleet  # noqa: E402


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_the_noise_is_read_right_where_one_parameter_explains_an_output():
    fleet = make_fleet(0)
    test = fleet[fleet.unit.isin([10, 11])].reset_index(drop=True)
    names = ["fouling", "dp_coeff"]
    estimated = jaxcal.calibrate("heat_exchanger", test, "ukf", theta=names)
    problem = estimated.problem
    assert problem.noise_source.startswith("estimated (one-step innovations")
    truth = np.asarray([NOISE[n] for n in problem.output_names])
    np.testing.assert_allclose(problem.noise_std, truth, rtol=0.15)
    given = jaxcal.calibrate("heat_exchanger", test, "ukf", theta=names, noise=NOISE)
    rmse = [
        np.sqrt(np.mean((r.theta - test[names].to_numpy())[r.valid] ** 2, axis=0))
        for r in (estimated, given)
    ]
    np.testing.assert_array_less(rmse[0], 1.1 * rmse[1])  # as good as the truth given
