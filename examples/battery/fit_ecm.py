"""Produce the constants of ``model.py`` from PyBaMM's Chen2020 cell (needs pybamm).

    python examples/battery/fit_ecm.py

1. OCV(SOC): ``U_p(y) - U_n(x)`` with ``x = x0 + soc (x100 - x0)``,
   ``y = y0 + soc (y100 - y0)`` (PyBaMM's 0 % / 100 % stoichiometries) on 2001
   SOC points; knot values on 41 uniform knots and Fritsch-Carlson (PCHIP) slopes
   from scipy; the maximum error of the Hermite curve on the 2001 points is printed.
2. Fresh cell: one drive cycle of ``make_data.py`` on the undegraded cell, no
   noise; R0, R1 and tau1 of the ECM (with ``Q`` = the fresh capacity and the OCV
   above) by nonlinear least squares on the voltage (scipy ``least_squares``).

Prints the Python block to paste into ``model.py``.
"""

from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

NUM_KNOTS = 41


def ocv_curve(num: int = 2001) -> tuple[np.ndarray, np.ndarray]:
    """``(soc [num], ocv [num])`` of the Chen2020 cell at 25 degC."""
    import pybamm

    p = pybamm.ParameterValues("Chen2020")
    x0, x100, y100, y0 = pybamm.lithium_ion.get_min_max_stoichiometries(p)
    soc = np.linspace(0.0, 1.0, num)

    def evaluate(fn, sto):
        return np.array([float(fn(pybamm.Scalar(s)).evaluate()) for s in sto])

    u_p = evaluate(p["Positive electrode OCP [V]"], y0 + soc * (y100 - y0))
    u_n = evaluate(p["Negative electrode OCP [V]"], x0 + soc * (x100 - x0))
    return soc, u_p - u_n


def fit_ocv_table():
    """Knot values and PCHIP slopes; prints the fit error."""
    import jax.numpy as jnp
    from scipy.interpolate import PchipInterpolator

    from model import ocv

    soc, volts = ocv_curve()
    knots = np.linspace(0.0, 1.0, NUM_KNOTS)
    values = np.interp(knots, soc, volts)
    slopes = PchipInterpolator(knots, values).derivative()(knots)
    fitted = np.asarray(ocv(jnp.asarray(soc), values, slopes))
    print(f"OCV table: max error {np.abs(fitted - volts).max() * 1e3:.2f} mV, "
          f"RMS {np.sqrt(np.mean((fitted - volts) ** 2)) * 1e3:.2f} mV "
          f"(2001 points)")  # fmt: skip
    return values, slopes


def fit_fresh_cell(values, slopes):
    """R0, R1, tau1 of the fresh cell from one noise-free SPMe drive cycle."""
    import jax
    import jax.numpy as jnp
    from scipy.optimize import least_squares

    import make_data
    import model

    p = make_data.parameters(1.0, 0.0)
    q_fresh = make_data.capacity(p)
    current = make_data.current_profile(np.random.default_rng(0), q_fresh, q_fresh)
    volts = make_data.simulate(p, current)["voltage"]
    w = jnp.stack([jnp.asarray(current), jnp.full(current.shape, make_data.DT)], 1)

    @jax.jit
    def predict(r0, r1, tau1):
        def body(z, wk):
            soc = z[0] - wk[0] * wk[1] / (3600.0 * q_fresh)
            decay = jnp.exp(-wk[1] / tau1)
            v1 = decay * z[1] + r1 * (1 - decay) * wk[0]
            v = model.ocv(soc, values, slopes) - r0 * wk[0] - v1
            return jnp.stack([soc, v1]), v

        return jax.lax.scan(body, jnp.array([make_data.SOC_START, 0.0]), w)[1]

    def residual(x):
        return np.asarray(predict(x[0], x[1], x[2])) - volts

    fit = least_squares(residual, [0.02, 0.01, 30.0], bounds=([1e-4, 1e-4, 1.0], [0.1, 0.1, 1000.0]))  # fmt: skip
    rms = np.sqrt(np.mean(fit.fun**2)) * 1e3
    print(f"fresh cell ({len(volts)} samples): R0 {fit.x[0]:.5f} Ohm, R1 "
          f"{fit.x[1]:.5f} Ohm, tau1 {fit.x[2]:.1f} s; voltage RMS {rms:.2f} mV")  # fmt: skip
    return (*fit.x, q_fresh)


def main() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)  # entry point
    values, slopes = fit_ocv_table()
    r0, r1, tau1, q_fresh = fit_fresh_cell(values, slopes)
    fmt = lambda a, d: ", ".join(f"{v:.{d}f}" for v in a)  # noqa: E731
    print("\n# ---- paste into model.py ----")
    print(f"OCV_VALUES = np.array([{fmt(values, 7)}])")
    print(f"OCV_SLOPES = np.array([{fmt(slopes, 4)}])")
    print(f"R0_FRESH = {r0:.5f}\nR1_FRESH = {r1:.5f}\nTAU1_FRESH = {tau1:.2f}")
    print(f"Q_FRESH = {q_fresh:.5f}")


if __name__ == "__main__":
    main()
