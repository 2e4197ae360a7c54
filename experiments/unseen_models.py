"""Three models the project had not seen before issue 27, written as a user would.

* ``pump``: a centrifugal pump against a valve (static). The pump curve
  ``H = h0 (1 - wear) (n / n0)^2 - c Q^2`` (affinity laws; Gülich, *Centrifugal
  Pumps*, 3rd ed., sec. 3.4) meets the system curve ``H = k Q^2 / v^2`` of a valve
  opened to ``v``; ``leak`` is the share of the flow lost through worn seals before
  the flow meter. Conditions: speed (rpm) and valve opening (-); parameters: impeller
  ``wear`` and seal ``leak``; outputs: measured flow (l/s), head (m) and shaft power
  (kW, at a fixed efficiency).
* ``motor``: a DC motor driving a load (with memory: the speed). Armature current
  ``i = (V - K w) / R`` (the armature's inductance neglected: its time constant is
  far below the sample), ``J dw/dt = K i - b w - tau``, integrated exactly over one
  sample for constant inputs (first-order linear ODE). Conditions: voltage (V) and
  load torque (N m); parameters: winding resistance ``R`` (grows with temperature and
  ageing) and bearing friction ``b``; outputs: speed (rad/s) and current (A).

* ``fan``: a ventilation fan blowing through a fouling filter and a damper (static,
  three parameters). The fan curve ``p = p0 (1 - wear) (n / n0)^2 - c Q^2`` (fan
  laws; Eck, *Fans*, 1973, ch. 2) meets the duct's ``p = k (1 + fouling) Q^2 / d^2``
  with the damper opened to ``d``; the shaft power ``Q p / eta`` reaches the meter
  through a drive that loses the share ``loss``. Conditions: speed (rpm) and damper
  opening (-); parameters: blade ``wear``, filter ``fouling`` (added resistance, a
  share of the clean duct's) and drive ``loss``; outputs: flow (m^3/s), pressure rise
  (Pa) and electrical power (kW). Added after the filter step's gain was chosen, as
  a check on a case nothing was tuned on. Its first version, with the duct's
  resistance not floored, stopped every UKF step: the sigma points reach
  ``fouling < -1``.

``make_fleet(name, ...)`` writes a fleet of units whose parameters drift at
unit-specific rates, with Gaussian output noise of ``NOISE[name]``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from jaxcal.model import Model

RHO_G, EFFICIENCY, N0 = 9.81, 0.7, 1500.0  # kN/m^3 per 1000 kg, -, rpm


def pump_outputs(w, theta):
    """``[flow l/s, head m, power kW]`` of a pump at ``w = [speed, valve]``."""
    speed, valve = w[0], w[1]
    wear, leak = theta[0], theta[1]
    h0, c, k = 40.0, 2.0e4, 1.0e4  # m, m/(m^3/s)^2, m/(m^3/s)^2 at a full opening
    shut = h0 * (1.0 - wear) * (speed / N0) ** 2
    q = jnp.sqrt(shut / (c + k / valve**2))  # m^3/s
    head = shut - c * q**2
    power = RHO_G * q * head / EFFICIENCY  # kW
    return jnp.stack([1e3 * q * (1.0 - leak), head, power])


def pump_model() -> Model:
    """The pump as a static :class:`~jaxcal.model.Model`."""
    return Model.from_function(
        pump_outputs,
        conditions={"speed": "rpm", "valve": "-"},
        parameters={"wear": (0.05, 0.0, 0.4, "-"), "leak": (0.02, 0.0, 0.2, "-")},
        outputs={"flow": "l/s", "head": "m", "power": "kW"},
        name="pump",
        condition_range=([800.0, 0.2], [1800.0, 1.0]),
    )


K_T, INERTIA, DT = 0.5, 0.05, 0.1  # N m / A, kg m^2, s


def motor_step(z, w, theta):
    """``(z', [speed, current])``: one sample of the DC motor (module doc)."""
    volt, torque = w[0], w[1]
    r, b = theta[0], theta[1]
    a = (K_T**2 / r + b) / INERTIA  # 1/s
    w_ss = (K_T * volt / r - torque) / (K_T**2 / r + b)
    speed = w_ss + jnp.exp(-a * DT) * (z[0] - w_ss)
    current = (volt - K_T * speed) / r
    return speed[None], jnp.stack([speed, current])


def motor_init(w, theta):
    """The speed at rest under ``w``."""
    r, b = theta[0], theta[1]
    return ((K_T * w[0] / r - w[1]) / (K_T**2 / r + b))[None]


def motor_model() -> Model:
    """The DC motor as a :class:`~jaxcal.model.Model` with memory."""
    return Model.from_step(
        motor_step,
        init_state=motor_init,
        states={"omega": "rad/s"},
        conditions={"voltage": "V", "torque": "N m"},
        parameters={"R": (1.0, 0.5, 2.0, "Ohm"), "b": (0.01, 0.002, 0.05, "N m s")},
        outputs={"speed": "rad/s", "current": "A"},
        name="motor",
        condition_range=([6.0, 0.0], [24.0, 2.0]),
    )


FAN_P0, FAN_N0, FAN_C, FAN_K, FAN_ETA = 800.0, 1200.0, 30.0, 40.0, 0.7  # Pa, rpm, ..


def fan_outputs(w, theta):
    """``[flow m^3/s, pressure Pa, power kW]`` of the fan at ``w = [speed, damper]``."""
    speed, damper = w[0], w[1]
    wear, fouling, loss = theta[0], theta[1], theta[2]
    shut = FAN_P0 * (1.0 - wear) * (speed / FAN_N0) ** 2
    # floored: the UKF's sigma points reach fouling < -1 (its prior 0.2 - sqrt(3) x
    # 1.5), where the resistance would turn negative and the flow NaN; jaxcal's
    # error said so ("outside the parameter bounds; make the model finite there")
    duct = FAN_K * jnp.maximum(1.0 + fouling, 0.05) / damper**2
    q = jnp.sqrt(shut / (FAN_C + duct))
    pressure = duct * q**2
    power = q * pressure / (FAN_ETA * (1.0 - 0.5 * wear)) / (1.0 - loss) / 1e3
    return jnp.stack([q, pressure, power])


def fan_model() -> Model:
    """The fan as a static :class:`~jaxcal.model.Model` with three parameters."""
    return Model.from_function(
        fan_outputs,
        conditions={"speed": "rpm", "damper": "-"},
        parameters={
            "wear": (0.02, 0.0, 0.4, "-"),
            "fouling": (0.2, 0.0, 3.0, "-"),
            "loss": (0.1, 0.02, 0.4, "-"),
        },  # fmt: skip
        outputs={"flow": "m^3/s", "pressure": "Pa", "power": "kW"},
        name="fan",
        condition_range=([600.0, 0.3], [1500.0, 1.0]),
    )


MODELS = {"pump": pump_model, "motor": motor_model, "fan": fan_model}
NOISE = {
    "pump": {"flow": 0.2, "head": 0.1, "power": 0.05},
    "motor": {"speed": 0.2, "current": 0.05},
    "fan": {"flow": 0.03, "pressure": 4.0, "power": 0.03},
}
START = {
    "pump": ([0.0, 0.0], [0.05, 0.03]),
    "motor": ([0.8, 0.005], [1.0, 0.01]),
    "fan": ([0.0, 0.0, 0.08], [0.05, 0.3, 0.12]),
}
RISE = {"pump": [0.25, 0.12], "motor": [0.6, 0.025], "fan": [0.15, 1.5, 0.1]}


def _schedule(rng, n, low, high):
    """Smooth random conditions inside ``[low, high]``."""
    cols = []
    for lo, hi in zip(low, high, strict=True):
        walk = np.cumsum(rng.normal(0.0, 1.0, n))
        walk = (walk - walk.min()) / max(np.ptp(walk), 1e-9)
        cols.append(lo + (hi - lo) * (0.1 + 0.8 * walk))
    return np.stack(cols, axis=1)


def make_fleet(name: str, units: int = 12, rows: int = 300, seed: int = 0):
    """A fleet of ``units`` x ``rows`` as a DataFrame with the true parameters."""
    model = MODELS[name]()
    rng = np.random.default_rng(seed)
    low, high = model.condition_range
    names = list(model.parameter_names)
    frames = []
    for unit in range(1, units + 1):
        t = np.arange(rows)
        start = rng.uniform(*START[name])
        rate = rng.uniform(0.4, 1.0, len(names))
        theta = start + np.asarray(RISE[name]) * rate * (t[:, None] / rows) ** 1.2
        w = _schedule(rng, rows, low, high)
        x = _simulate(model, w, theta)
        noise = np.array([NOISE[name][o] for o in model.output_names])
        x = x + noise * rng.normal(size=x.shape)
        frame = pd.DataFrame(w, columns=list(model.condition_names))
        frame[list(model.output_names)] = x
        frame["unit"], frame["time"] = unit, t
        frame[names] = theta
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def _simulate(model: Model, w, theta):
    w, theta = jnp.asarray(w), jnp.asarray(theta)
    static = {"pump": pump_outputs, "fan": fan_outputs}
    if model.name in static:
        return np.asarray(jax.vmap(static[model.name])(w, theta))

    def body(z, inputs):
        return motor_step(z, *inputs)

    return np.asarray(jax.lax.scan(body, motor_init(w[0], theta[0]), (w, theta))[1])
