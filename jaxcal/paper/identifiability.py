"""Which part of a calibrator's theta error the sensors cannot see.

On Dataset #2 every method, the exact-model UKF and least squares included, ends near
the same theta RMSE. The reason is the measurement, not the methods: with P45 (between
the turbines) unmeasured, one joint change of the turbine modifiers moves the measured
sensors very little (README, "The engine model"). This module makes that a number.

For a unit with samples t = 1..T, operating conditions w_t and true theta, the
information a noise-free sensor vector carries about theta is, to first order, the
Gauss-Newton matrix of the normalised model (sensors in training stds, Problem.norm)

    G = (1 / T) sum_t J_t^T J_t,    J_t = d(F(w_t, theta) / std) / d theta,

whose eigenvector v_min of the smallest eigenvalue is the weakest direction: a step
of size a along it moves the sensor vector by a * sqrt(lambda_min) training stds (its
norm over the sensors, RMS over the flight), against a * sqrt(lambda_max) along the
strongest one. Each method's
error e_t = theta_hat_t - theta_t is split into its component along v_min of its unit
and the rest; if most of the squared error lies along v_min, no calibrator that uses
these sensors can do much better, and the differences between methods there come from
where each one's prior or training puts that unseen component.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.data.padded import Padded
from jaxcal.paper.compare import stacked
from jaxcal.paper.methods import engine_outputs, measure_declared
from jaxcal.problem import Problem


def normalised_jacobians(
    engine, problem: Problem, w: np.ndarray, theta: np.ndarray, *, chunk: int = 1024
) -> np.ndarray:
    """``[N, S, P]`` d(F / std)/d theta at ``N`` samples (float64, jitted, vmapped).

    Raises:
        ValueError: when F does not solve at a sample (its Jacobian would be NaN).
    """
    w = np.asarray(w, np.float64)
    theta = np.asarray(theta, np.float64)
    out = []
    with jax.enable_x64(True):  # the engine's Newton solve needs float64
        measure = measure_declared(
            lambda ww, th: engine_outputs(engine, ww, th),  # the shared traced F
            problem.theta_base, problem.theta_names, problem.output_names,
        )  # fmt: skip
        std = jnp.asarray(problem.norm.x_std, jnp.float64)
        jac = jax.jit(
            jax.vmap(jax.jacfwd(lambda ww, th: measure(ww, th) / std, argnums=1))
        )
        for i in range(0, len(w), chunk):  # chunks bound memory; one compiled shape
            wi, ti = w[i : i + chunk], theta[i : i + chunk]
            pad = chunk - len(wi)
            wi = np.concatenate([wi, np.repeat(wi[-1:], pad, 0)])
            ti = np.concatenate([ti, np.repeat(ti[-1:], pad, 0)])
            out.append(np.asarray(jac(wi, ti))[: chunk - pad])
    j = np.concatenate(out)
    bad = ~np.isfinite(j).all(axis=(1, 2))
    if bad.any():
        raise ValueError(
            f"F has no finite Jacobian at {int(bad.sum())} of {len(j)} samples "
            f"(first: w = {w[np.argmax(bad)].tolist()})"
        )
    return j


def weak_directions(
    jacobians: np.ndarray, starts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per unit: eigenvalues ``[U, P]`` (ascending) and weakest direction ``[U, P]``.

    Args:
        jacobians: ``[N, S, P]`` stacked over units.
        starts: ``[U]`` index of each unit's first sample.
    """
    ends = np.append(starts[1:], len(jacobians)).astype(int)
    eig, vmin = [], []
    for a, b in zip(starts.astype(int), ends, strict=True):
        j = jacobians[a:b]
        g = np.einsum("tsp,tsq->pq", j, j) / len(j)
        lam, vec = np.linalg.eigh(g)
        eig.append(lam)
        vmin.append(vec[:, 0])
    return np.array(eig), np.array(vmin)


def split_error(
    theta_hat: np.ndarray, truth: np.ndarray, vmin: np.ndarray, starts: np.ndarray
) -> dict:
    """A method's theta RMSE, and the parts along each unit's weakest direction and
    across it (RMS per parameter, so that the squares add up to the total)."""
    err = np.asarray(theta_hat, np.float64) - np.asarray(truth, np.float64)
    counts = np.diff(np.append(starts, len(err))).astype(int)
    v = np.repeat(vmin, counts, axis=0)
    along = np.sum(err * v, axis=1, keepdims=True) * v
    p = err.shape[1]
    total = float(np.sqrt(np.mean(err**2)))
    weak = float(np.sqrt(np.sum(along**2) / (len(err) * p)))
    rest = float(np.sqrt(np.sum((err - along) ** 2) / (len(err) * p)))
    share = weak**2 / total**2 if total > 0 else 0.0
    return {"theta_rmse": total, "along_weakest": weak, "across_weakest": rest,
            "share_along_weakest": share}  # fmt: skip


def identifiability_study(
    engine, problem: Problem, units: Padded, traces: dict, *, stride: int = 1
) -> dict:
    """The weakest direction of every test unit and each method's error split.

    Args:
        engine: float64 engine of the problem.
        problem: sensors, declared parameters, normalisation.
        units: the scored test units (``[U, T, ...]``).
        traces: method name -> ``theta_hat [N, P]`` over the units' valid samples in
            order (every ``stride``-th one, as the stored figure traces keep them).
        stride: sample stride of the traces.

    Returns:
        JSON-ready: eigenvalue spread, the weakest direction averaged over units (sign
        fixed), and per method the RMSE split of :func:`split_error`.
    """
    w, starts = stacked(units.w, units.mask)
    truth, _ = stacked(units.theta, units.mask)
    w, truth = w[::stride], truth[::stride]
    starts = np.ceil(starts / stride).astype(int)
    jac = normalised_jacobians(engine, problem, w, truth)
    eig, vmin = weak_directions(jac, starts)
    vmin = vmin * np.sign(vmin[:, [int(np.argmax(np.abs(vmin.mean(0))))]])
    methods = {}
    for name, theta_hat in traces.items():
        if len(theta_hat) != len(truth):
            raise ValueError(
                f"trace of {name} has {len(theta_hat)} samples, expected {len(truth)}"
            )
        methods[name] = split_error(theta_hat, truth, vmin, starts)
    # What knowing everything but the weak component, and guessing that one by its
    # mean over the scored units, would score (RMS per parameter): the level a method
    # reaches when the sensors tell it nothing along v_min.
    counts = np.diff(np.append(starts, len(truth))).astype(int)
    comp = np.sum(truth * np.repeat(vmin, counts, axis=0), axis=1)
    floor = float(np.sqrt(np.mean((comp - comp.mean()) ** 2) / truth.shape[1]))
    sens = np.sqrt(np.maximum(eig, 0.0))
    return {
        "prior_mean_along_weakest": floor,
        "theta_names": list(problem.theta_names),
        "num_units": len(starts),
        "num_samples": len(truth),
        "weakest_direction_mean": vmin.mean(0).tolist(),
        # change of the sensor vector (norm, training stds) per unit step along it
        "sensitivity_weakest_median": float(np.median(sens[:, 0])),
        "sensitivity_strongest_median": float(np.median(sens[:, -1])),
        "condition_median": float(np.median(sens[:, -1] / sens[:, 0])),
        "methods": methods,
    }
