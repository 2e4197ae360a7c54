"""A leaky tank, the small static model the front-door tests calibrate.

Heated by ``heat`` with inflow ``inflow``; its leak rate and heat loss are the
parameters; level, temperature and outflow are measured. Data: ``make_frame`` draws
units whose leak drifts, with Gaussian noise :data:`NOISE`, rows shuffled.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

import jaxcal

NOISE = np.array([0.02, 0.02, 0.05])


def tank(w, theta):
    """A leaky tank heated by w[0] with inflow w[1]: level, temperature, outflow."""
    heat, inflow = w[0], w[1]
    leak, loss = theta[0], theta[1]
    level = inflow / leak
    temp = 20.0 + heat / (inflow * (1.0 + loss))
    return jnp.stack([level, temp, leak * level * (1.0 - 0.1 * loss)])


def tank_model(fn=tank, name="tank", condition_range=([0.0, 0.1], [50.0, 5.0])):
    """``fn`` declared as the tank (``condition_range=None``: no input box)."""
    return jaxcal.Model.from_function(
        fn,
        conditions={"heat": "kW", "inflow": "kg/s"},
        parameters={"leak": (1.0, 0.5, 2.0, "1/s"), "loss": (0.1, 0.0, 0.5)},
        outputs={"level": "m", "temp": "degC", "outflow": "kg/s"},
        condition_range=condition_range,
        name=name,
    )


MODEL = tank_model()


def make_frame(num_units=3, length=60, seed=0):
    """``num_units`` units of ``length`` rows, shuffled; true leak and loss columns."""
    rng = np.random.default_rng(seed)
    n = num_units * length
    t = np.tile(np.arange(length), num_units)
    frame = pd.DataFrame(
        {"heat": rng.uniform(5, 30, n), "inflow": rng.uniform(0.5, 2.0, n)}
    )
    leak = 1.0 + 0.3 * t / length + 0.1 * np.repeat(np.arange(num_units), length)
    loss = np.full(n, 0.2)
    x = np.asarray(
        jax.vmap(tank)(frame.to_numpy(), np.stack([leak, loss], 1))
    ) + NOISE * rng.standard_normal((n, 3))
    for j, name in enumerate(MODEL.output_names):
        frame[name] = x[:, j]
    frame["unit"], frame["time"] = np.repeat(np.arange(num_units), length), t
    frame["leak"], frame["loss"] = leak, loss
    return frame.sample(frac=1.0, random_state=1).reset_index(drop=True)  # shuffled
