"""The peers on the same ECM and data: dynamax's UKF and PyBOP's fit (optional extras).

* dynamax (``pip install dynamax``): its additive-noise unscented Kalman filter for
  nonlinear Gaussian state-space models (``dynamax.nonlinear_gaussian_ssm``) on the
  augmented state ``[soc, v_rc1, R0, Q]`` (random-walk parameters), with exactly the
  settings of jaxcal's joint UKF (:data:`UKF`): prior, random-walk and measurement
  noise in the same physical units. dynamax conditions ``y_t`` on ``h(z_t, u_t)``
  and then predicts with ``f(z_t, u_{t+1})``, so its latent ``z_t`` is the ECM
  state *after* sample ``t``; the initial mean is the ECM's initial state stepped
  once with ``u_0`` (exact, no shift error).
* PyBOP (``pip install pybop``): PyBaMM's Thevenin ECM with the same OCV table
  (cubic interpolant), R1 and tau1, fitted for ``R0`` and the capacity on each
  cycle separately (a batch fit per window, SciPy's minimiser); the cycle starts at
  rest at SOC 0.9 as in the data. PyBaMM interpolates the current linearly between
  samples where the data hold it constant over each step: a small model difference
  at pulse edges.

A peer that does not install or run is reported (``{"error": ...}``), never fatal.
"""

from __future__ import annotations

import time

import numpy as np

import model as ecm

THETA = ("R0", "Q")
# Joint-UKF settings shared by jaxcal and dynamax (physical units per step).
UKF = {
    "noise": 0.02,  # [V] voltage std: 2 mV sensor + ~18 mV ECM-vs-SPMe model error
    "prior_std": 0.25,  # half-widths of the box (R0 0.0098 Ohm, Q 0.44 Ah)
    "q": 5e-4,  # random walk per step, half-widths (R0 2e-5 Ohm, Q 8.7e-4 Ah)
    "state_std": {"soc": 0.02, "v_rc1": 0.01},  # initial state std
    "state_q": {"soc": 1e-4, "v_rc1": 1e-3},  # process noise on the states per step
}


def _half_width() -> np.ndarray:
    low, high = ecm.MODEL.bounds
    idx = ecm.MODEL.parameter_index(THETA)
    return (high[idx] - low[idx]) / 2.0


def make_dynamax_filter():
    """``track(current [T], dt [T], voltage [T]) -> (mean [T, 4], std [T, 4])``:
    dynamax's UKF on ``[soc, v_rc1, R0, Q]`` (not jitted; jit or vmap it)."""
    import jax.numpy as jnp
    from dynamax.nonlinear_gaussian_ssm import (
        ParamsNLGSSM,
        UKFHyperParams,
        unscented_kalman_filter,
    )

    half = _half_width()
    fixed = {"R1": ecm.R1_FRESH, "tau1": ecm.TAU1_FRESH}

    def theta_full(z):
        return jnp.stack([z[2], fixed["R1"], fixed["tau1"], z[3]])

    def dynamics(z, u):
        state, _ = ecm.step(z[:2], u, theta_full(z))
        return jnp.concatenate([state, z[2:]])

    def emission(z, u):
        # z is the state after the sample; V = OCV(soc) - R0 I - v_rc1
        return (ecm.ocv(z[0]) - z[2] * u[0] - z[1])[None]

    prior = np.array([ecm.R0_FRESH, ecm.Q_FRESH])
    var0 = np.concatenate(
        [[UKF["state_std"]["soc"] ** 2, UKF["state_std"]["v_rc1"] ** 2],
         (UKF["prior_std"] * half) ** 2]
    )  # fmt: skip
    var_q = np.concatenate(
        [[UKF["state_q"]["soc"] ** 2, UKF["state_q"]["v_rc1"] ** 2],
         (UKF["q"] * half) ** 2]
    )  # fmt: skip
    hyper = UKFHyperParams(alpha=1.0, beta=2.0, kappa=0.0)  # jaxcal's defaults

    def track(current, dt, voltage):
        u = jnp.stack([current, dt], axis=1)
        z_init = jnp.asarray([ecm.SOC_0, 0.0, *prior])
        params = ParamsNLGSSM(
            initial_mean=dynamics(z_init, u[0]),
            initial_covariance=jnp.diag(var0),
            dynamics_function=dynamics,
            dynamics_covariance=jnp.diag(var_q),
            emission_function=emission,
            emission_covariance=jnp.eye(1) * UKF["noise"] ** 2,
        )
        post = unscented_kalman_filter(
            params, voltage[:, None], hyper, inputs=u,
            output_fields=["filtered_means", "filtered_covariances"],
        )  # fmt: skip
        std = jnp.sqrt(jnp.diagonal(post.filtered_covariances, axis1=1, axis2=2))
        return post.filtered_means, std

    return track


def time_per_sample(fn, *args, repeats: int = 3) -> float:
    """Median seconds per call of a jitted ``fn`` after compilation."""
    import jax

    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def pybop_fit(frame, cycles) -> dict:
    """PyBOP's per-cycle fit of ``R0`` and the capacity on one unit's ``frame``.

    Returns ``{"cycle": [...], "R0": [...], "Q": [...], "seconds": [...]}`` or
    ``{"error": "..."}`` when PyBOP is missing or fails.
    """
    try:
        import pybamm
        import pybop
    except Exception as exc:  # an optional peer: report, do not fail
        return {"error": f"import failed: {type(exc).__name__}: {exc}"}
    out = {"cycle": [], "R0": [], "Q": [], "seconds": [], "version": pybop.__version__}
    try:
        knots = np.linspace(0.0, 1.0, ecm.OCV_VALUES.shape[0])

        def ocv_fn(soc):
            return pybamm.Interpolant(knots, ecm.OCV_VALUES, soc, interpolator="cubic")

        model = pybamm.equivalent_circuit.Thevenin()
        for k in cycles:
            rows = frame[frame.cycle == k]
            t = rows.time.to_numpy() - rows.time.to_numpy()[0] + rows.dt.to_numpy()[0]
            dataset = pybop.Dataset(
                {
                    "Time [s]": np.concatenate([[0.0], t]),
                    "Current function [A]": np.concatenate([[rows.current.iloc[0]], rows.current]),  # fmt: skip
                    "Voltage [V]": np.concatenate([[rows.voltage.iloc[0]], rows.voltage]),  # fmt: skip
                }
            )
            values = model.default_parameter_values
            values.update(
                {
                    "Open-circuit voltage [V]": ocv_fn,  # OCV(soc), no temperature
                    "Entropic change [V/K]": 0.0,
                    "Initial SoC": ecm.SOC_0,
                    "Element-1 initial overpotential [V]": 0.0,
                    "R1 [Ohm]": ecm.R1_FRESH,
                    "C1 [F]": ecm.TAU1_FRESH / ecm.R1_FRESH,
                    "Upper voltage cut-off [V]": 5.0,
                    "Lower voltage cut-off [V]": 1.5,
                    "R0 [Ohm]": pybop.Parameter(initial_value=ecm.R0_FRESH, bounds=[0.002, 0.08]),  # fmt: skip
                    "Cell capacity [A.h]": pybop.Parameter(initial_value=ecm.Q_FRESH, bounds=[2.5, 6.0]),  # fmt: skip
                },
                check_already_exists=False,
            )
            start = time.perf_counter()
            simulator = pybop.pybamm.Simulator(model, parameter_values=values, protocol=dataset)  # fmt: skip
            problem = pybop.Problem(simulator, pybop.SumSquaredError(dataset))
            result = pybop.SciPyMinimize(problem).run()
            out["seconds"].append(time.perf_counter() - start)
            out["cycle"].append(int(k))
            best = result.best_inputs  # by name: PyBOP orders the vector itself
            out["R0"].append(float(best["R0 [Ohm]"]))
            out["Q"].append(float(best["Cell capacity [A.h]"]))
            print(f"  pybop cycle {k}: R0 {out['R0'][-1]:.5f} Ohm, Q {out['Q'][-1]:.3f} Ah "
                  f"({out['seconds'][-1]:.1f} s)", flush=True)  # fmt: skip
    except Exception as exc:  # report the failure with its message
        out["error"] = f"{type(exc).__name__}: {str(exc)[:300]}"
    return out
