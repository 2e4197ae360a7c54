"""A :class:`jaxcal.problem.Problem` in the turbofan's vocabulary for the paper tests,
whose methods evaluate their own (toy) engine and read only the problem's names, box
and normalisation."""

import jax.numpy as jnp
import numpy as np

from jaxcal.model import Model
from jaxcal.models.turbofan.physics.constants import (
    CONDITION_NAMES,
    HEALTH_NAMES,
    SENSOR_NAMES,
)
from jaxcal.problem import InputRange, Normalisation, Problem


def paper_problem(name, outputs, theta_names, theta_low, theta_high, x_mean, x_std):
    """The problem of a toy turbofan-named model (``name``) on ``outputs``."""
    model = Model.from_function(
        lambda w, theta: jnp.zeros(len(SENSOR_NAMES)),  # never evaluated
        conditions=CONDITION_NAMES,
        parameters={h: (0.0, -1.0, 1.0) for h in HEALTH_NAMES},
        outputs=SENSOR_NAMES,
        name=name,
    )
    x_mean, x_std = np.asarray(x_mean, float), np.asarray(x_std, float)
    num_w = len(CONDITION_NAMES)
    return Problem(
        model=model,
        theta_names=tuple(theta_names),
        output_names=tuple(outputs),
        theta_base=np.zeros(len(HEALTH_NAMES)),
        theta_low=np.asarray(theta_low, float),
        theta_high=np.asarray(theta_high, float),
        norm=Normalisation(np.zeros(num_w), np.ones(num_w), x_mean, x_std),
        noise_std=0.01 * x_std,
        input_range=InputRange(
            np.full(num_w, -np.inf), np.full(num_w, np.inf), x_mean - 1e9, x_mean + 1e9
        ),
    )
