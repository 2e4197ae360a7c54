"""Is the model passed to a trained run the one it was trained on?

``jaxcal.calibrate(model, data, "policy", run=...)`` reads the data with the model it
is given, but the policy runs with the run's own model (its stored copy,
:mod:`jaxcal.training.model_source`). :func:`check_run_model` makes a difference
between the two an error rather than a silent substitution: first the variables'
names (conditions, parameters, outputs, states), then the outputs of both models at
a few probe points — three operating points across the run's training range of the
conditions, stepped through from the initial state at three parameter vectors across
the run's box (undeclared parameters at their held values). A registered model of
the same name is the installed jaxcal's on both sides and is not probed (the
turbofan's solver would compile twice for nothing).
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.model import Model

_FRACTIONS = np.array([0.25, 0.5, 0.75])  # where in the ranges the probes sit
# Same outputs: within this relative distance of the output's scale over the probes.
_RTOL = 1e-5


def _probe_inputs(run) -> tuple[np.ndarray, np.ndarray]:
    """``(w [3, W], theta [3, P_all])``: the probe points of ``run``'s problem."""
    problem = run.problem
    model = problem.model
    low = high = None
    if problem.input_range is not None:
        low, high = problem.input_range.w_low, problem.input_range.w_high
    elif model.condition_range is not None:
        low, high = (np.where(np.isfinite(b), b, 0.0) for b in model.condition_range)
    if low is None:  # nothing known of the conditions: around 1
        num = len(model.conditions)
        low, high = np.full(num, 0.5), np.full(num, 1.5)
    w = low + _FRACTIONS[:, None] * (np.asarray(high) - np.asarray(low))
    theta = np.tile(np.asarray(problem.theta_base, np.float64), (3, 1))
    box = problem.theta_low + _FRACTIONS[:, None] * (
        problem.theta_high - problem.theta_low
    )
    theta[:, list(problem.theta_index)] = box
    return w, theta


def _outputs(model: Model, w: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``[3 (theta), 3 (w), S_all]``: the model stepped through ``w`` at each theta."""

    def along(theta_j):
        w_j = jnp.asarray(w, theta_j.dtype)

        def step(state, w_t):
            state, x, _ = model.step(state, w_t, theta_j)
            return state, x

        return jax.lax.scan(step, model.init_state(w_j[0], theta_j), w_j)[1]

    return np.asarray(jax.jit(jax.vmap(along))(jnp.asarray(theta)), np.float64)


def _difference(run, given: Model) -> str | None:
    """What differs between ``run``'s model and ``given``, or ``None``."""
    own = run.problem.model
    for field in ("condition_names", "parameter_names", "output_names", "state_names"):
        a, b = getattr(own, field), getattr(given, field)
        if tuple(a) != tuple(b):
            return f"its {field} are {list(a)}, the given model's {list(b)}"
    source = getattr(run, "model_source", None) or {}
    if source.get("kind") == "registered" and given.name == source.get("name"):
        return None
    w, theta = _probe_inputs(run)
    a = _outputs(own, w, theta)
    try:
        b = _outputs(given, w, theta)
    except Exception as err:  # the user's code: name it rather than crash
        return f"it fails at the probe points ({type(err).__name__}: {err})"
    if a.shape != b.shape:
        return (
            f"its outputs have shape {list(a.shape[2:])}, the given model's "
            f"{list(b.shape[2:])}"
        )
    scale = np.nanmax(np.abs(a), axis=(0, 1)) + np.finfo(np.float32).tiny
    close = np.isclose(a, b, rtol=_RTOL, atol=_RTOL * scale, equal_nan=True)
    if close.all():
        return None
    j, i, s = np.argwhere(~close)[0]
    where = f"w={_short(w[i])}, theta={_short(theta[j])}"
    if own.is_stateful:
        where += f", step {i + 1} from the initial state"
    return (
        f"at the probe point {where} its output {own.output_names[s]!r} is "
        f"{a[j, i, s]:.6g}, the given model's {b[j, i, s]:.6g}"
    )


def _short(values: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.4g}" for v in values) + "]"


def check_run_model(run, given: Model) -> None:
    """Refuse ``given`` unless it is ``run``'s own model by names and outputs.

    Args:
        run: a :class:`~jaxcal.calibrators.methods.policy.loading.LoadedRun`.
        given: the model a caller passed along with the run.

    Raises:
        ValueError: naming the run, its model and the first difference found.

    Warns:
        UserWarning: same variables and outputs under another model name.
    """
    own = run.problem.model
    if given is own:
        return
    difference = _difference(run, given)
    if difference is not None:
        raise ValueError(
            f"run {run.run_dir} was trained on model {own.name!r} and calibrates with "
            f"it; the model given ({given.name!r}) differs: {difference}. Pass the "
            "run's own model (jaxcal.deploy.load_run(run).problem.model) or retrain "
            "the run on the new model"
        )
    if given.name != own.name:
        warnings.warn(
            f"run {run.run_dir} was trained on model {own.name!r}; the model given is "
            f"named {given.name!r} but has the same variables and outputs at the "
            "probe points: the run's own model is used",
            stacklevel=3,
        )
