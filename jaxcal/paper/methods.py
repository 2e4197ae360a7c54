"""Every method of the paper's comparison behind one calibrator interface.

For one data set (the run's :class:`~jaxcal.problem.Problem`: model, outputs, declared
parameters, action box, training normalisation) this module builds the paper's
methods and ours as :class:`Method` objects, each a ``Calibrator`` factory plus one
jitted fleet runner (``lax.scan`` over time, ``vmap`` over units,
:func:`~jaxcal.calibrators.interface.run_fleet`):

The UKF and least squares are the method table's (:mod:`jaxcal.calibrators.methods`)
on the suite's perturbable F:

* UKF on the physics F (Tian et al. §2.3, eq. ukf; q = r = 0.01 on normalised
  outputs and on parameters scaled by the half-width of the action box);
* sliding-window least squares on F (ours, beyond the paper);
* the E2E network theta_t = G(w_t, x_t, x_{t-1}) (§2.4, eq. e2e) from trained weights;
* a trained RL policy (CLAC, LAC, SAC) from its run folder (:mod:`jaxcal.deploy`).

Model inadequacy (§5, "Robustness to Environment Uncertainty"): the paper perturbs
the *output of the model the calibrator uses* — F(w, theta) x alpha and
F(w, theta) + eta, eta ~ N(0, alpha_eta) — not the data. Every model-based method here
therefore takes a traced ``bias`` and ``noise_sigma``: the UKF and least squares apply
them to F, a policy to its transition D (or F). The noise is in units of each sensor's
training std and is drawn afresh for every model evaluation (a stochastic simulator);
``bias = 1, noise_sigma = 0`` leaves the model bit for bit unchanged. Because the
settings are traced arguments, the clean and perturbed runs share one compiled program.
The E2E network has no model; it ignores both settings.

Guarded samples: every method runs with a :class:`~jaxcal.calibrators.interface.
SampleCheck` — the engine's envelope for the UKF, least squares and E2E, the training
range for a policy — so a NaN or out-of-range sample is skipped and flagged
(``CalOutput.valid`` / ``.reason``), never fed to the model.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import lax

from jaxcal.calibrators.interface import (
    Calibrator,
    MeasureFn,
    SampleCheck,
    run_fleet,
)
from jaxcal.calibrators.methods import method_of
from jaxcal.calibrators.methods.e2e.network import E2EParams, make_e2e_calibrator
from jaxcal.calibrators.methods.ls.window import LeastSquaresConfig
from jaxcal.calibrators.methods.policy.calibrator import make_policy_calibrator
from jaxcal.calibrators.methods.policy.trained import run_check
from jaxcal.calibrators.programs.compiled import inputs_of
from jaxcal.calibrators.ukf import UKFConfig
from jaxcal.envs.memory import HintedDynamics
from jaxcal.envs.tracking import Dynamics
from jaxcal.models.turbofan.physics.constants import health_index, sensor_index
from jaxcal.problem import Problem
from jaxcal.typedefs import Array, PRNGKey

BuildFn = Callable[[Array, Array], Calibrator]  # (bias [], noise_sigma []) -> method


class Method(NamedTuple):
    """One calibration method, ready to run.

    Attributes:
        name: label in tables and figures.
        build: ``build(bias, noise_sigma) -> Calibrator`` (pure; call it under jit).
        run: jitted ``run(w [U,T,W], x [U,T,S], mask [U,T], keys [U], bias [],
            noise_sigma []) -> CalOutput``, compiled once per shape.
        dtype: float dtype the method computes in (float64 around the engine).
        model_free: True when ``xhat`` is not produced (E2E): it is NaN and the
            caller evaluates F at the inferred theta for tracking scores.
        info: JSON-ready settings for the report.
        check: the valid input box the runner flags samples against (``None``:
            finiteness only).
        deploy_fn: ``deploy_fn() -> Calibrator``, the method as a user deploys it on
            one stream, one sample per call: the clean model (no perturbation, so no
            noise key in its state) and, where the model can, its solver
            warm-started from the previous sample (``warm``); what the latency
            measures. ``None``: ``build(1, 0)``, key and all.
        warm: ``deploy_fn``'s model solve is warm-started along the stream.
    """

    name: str
    build: BuildFn
    run: Callable
    dtype: Any
    model_free: bool
    info: dict
    check: SampleCheck | None = None
    deploy_fn: Callable[[], Calibrator] | None = None
    warm: bool = False

    def deploy(self) -> Calibrator:
        """The deployed single-stream form (``deploy_fn``, else ``build(1, 0)``)."""
        if self.deploy_fn is None:
            return self.build(
                jnp.asarray(1.0, self.dtype), jnp.asarray(0.0, self.dtype)
            )
        return self.deploy_fn()


def make_method(
    name: str,
    build: BuildFn,
    dtype,
    info: dict,
    *,
    model_free: bool = False,
    check: SampleCheck | None = None,
    deploy_fn: Callable[[], Calibrator] | None = None,
    warm: bool = False,
) -> Method:
    """Wrap a calibrator factory with its jitted fleet runner (guarded by
    ``check``; the returned ``CalOutput`` carries ``valid`` and ``reason``).
    ``deploy_fn``, ``warm``: its deployed single-stream form (:class:`Method`)."""

    def run(w, x, mask, keys, bias, noise_sigma):
        return run_fleet(build(bias, noise_sigma), w, x, mask, keys=keys, check=check)

    return Method(
        name, build, jax.jit(run), np.dtype(dtype), model_free, info, check,
        deploy_fn, warm,
    )  # fmt: skip


# ------------------------------------------------------------------ perturbations


def evaluation_key(key: PRNGKey, *arrays: Array) -> PRNGKey:
    """A key unique to the values of ``arrays`` (one fresh draw per model input).

    The bits of every entry are folded in, so two evaluations at different
    ``(w, theta)`` — the UKF's sigma points, the samples of a least-squares window —
    draw independent noise while a repeated evaluation draws the same.
    """
    for array in arrays:
        bits = lax.bitcast_convert_type(
            lax.stop_gradient(jnp.ravel(array)).astype(jnp.float32), jnp.uint32
        )
        for i in range(bits.shape[0]):  # static, a handful of entries
            key = jax.random.fold_in(key, bits[i])
    return key


def perturb_output(
    x: Array, key: PRNGKey, bias: Array, noise_sigma: Array, std: Array
) -> Array:
    """Model inadequacy on one output: ``x * bias + noise_sigma * std * eps``.

    Args:
        x: ``[S]`` model output.
        key: PRNG key of this evaluation.
        bias: ``[]`` multiplicative bias alpha (paper: 1.02; 1 = none).
        noise_sigma: ``[]`` noise std alpha_eta in units of ``std`` (paper: 0.1).
        std: ``[S]`` training std of each sensor.

    Returns:
        ``[S]`` perturbed output (exactly ``x`` for ``bias = 1, noise_sigma = 0``).
    """
    eps = jax.random.normal(key, x.shape, dtype=x.dtype)
    return x * bias.astype(x.dtype) + (noise_sigma * std).astype(x.dtype) * eps


@struct.dataclass
class KeyedState:
    """State of a calibrator whose model draws noise: the inner state plus a key."""

    inner: Any
    key: PRNGKey


def with_step_key(make: Callable[[PRNGKey], Calibrator]) -> Calibrator:
    """A calibrator that hands a fresh key to its model on every step.

    Args:
        make: ``make(key) -> Calibrator`` whose model draws its noise from ``key``
            (its ``init`` must not depend on the key).

    Returns:
        ``Calibrator``; ``init`` needs a PRNG key, ``step`` splits it each sample.
    """

    def init(key: PRNGKey | None, w0: Array, x0: Array) -> KeyedState:
        if key is None:
            raise ValueError("a calibrator with a stochastic model needs a PRNG key")
        return KeyedState(inner=make(key).init(None, w0, x0), key=key)

    def step(state: KeyedState, w_t: Array, x_t: Array):
        key, key_step = jax.random.split(state.key)
        inner, out = make(key_step).step(state.inner, w_t, x_t)
        return KeyedState(inner=inner, key=key), out

    return Calibrator(init=init, step=step)


def perturbed_dynamics(
    dynamics: Dynamics, key: PRNGKey, bias: Array, noise_sigma: Array, std: Array
) -> Dynamics:
    """``dynamics`` (the tracking MDP's transition) with its output perturbed by
    :func:`perturb_output`; one draw per call, from ``key``."""

    def perturbed(dyn_params, w, xhat, theta):
        out = dynamics(dyn_params, w, xhat, theta)
        return perturb_output(out, key, bias, noise_sigma, std)

    if isinstance(dynamics, HintedDynamics):  # keep the model's warm start
        return dynamics.map_output(
            lambda out: perturb_output(out, key, bias, noise_sigma, std)
        )
    return perturbed


# ------------------------------------------------------------------ model-based


def _engine_outputs(engine, w: Array, theta_full: Array) -> Array:
    return engine.evaluate(w, theta_full)[0]


# Jitted (against the style's "entry points only") because nested jits keep their
# traced jaxpr: the engine's large Newton graph is traced and batched once per
# process and vmap pattern, not once per method, variant and data set (~5 s each).
engine_outputs = jax.jit(_engine_outputs)


def measure_declared(
    measure_full: Callable[[Array, Array], Array],
    theta_base: Array,
    declared_idx: Sequence[int] | Sequence[str],
    sensor_idx: Sequence[int] | Sequence[str] | None = None,
) -> MeasureFn:
    """Restrict a full-parameter model to the declared parameters and chosen sensors.

    Model-based calibrators estimate only the ``P`` declared parameters; the others are
    held at ``theta_base``. Because the declared vector is scattered into the full one,
    ``jax.jacfwd`` of the result costs ``P`` tangent sweeps, not one per full parameter.

    Args:
        measure_full: ``F(w [Wd], theta_full [P_full]) -> x_full [S_full]`` (for the
            engine: ``lambda w, th: engine.evaluate(w, th)[0]``).
        theta_base: ``[P_full]`` values of all parameters (undeclared ones stay here).
        declared_idx: positions in ``theta_full`` of the declared parameters, or their
            names in the turbofan's
            ``jaxcal.models.turbofan.physics.constants.HEALTH_NAMES``.
        sensor_idx: positions in ``x_full`` of the sensors to return, or their names in
            ``SENSOR_NAMES``; ``None`` keeps all.

    Returns:
        ``measure(w [Wd], theta [P]) -> x [S]``.
    """
    theta_base = jnp.asarray(theta_base)
    if theta_base.ndim != 1:
        raise ValueError(f"theta_base must be [P_full], got shape {theta_base.shape}")
    declared = _as_index(
        declared_idx, health_index, "declared_idx", theta_base.shape[0]
    )
    sensors = (
        None
        if sensor_idx is None
        else _as_index(sensor_idx, sensor_index, "sensor_idx", None)
    )

    def measure(w: Array, theta: Array) -> Array:
        theta_full = theta_base.astype(theta.dtype).at[declared].set(theta)
        x_full = measure_full(w, theta_full)
        return x_full if sensors is None else x_full[sensors]

    return measure


def _as_index(idx, from_names, field: str, size: int | None) -> np.ndarray:
    """Names or integers -> a unique 1-D int array, with a clear error otherwise."""
    idx = list(idx)
    if not idx:
        raise ValueError(f"{field} must name at least one entry")
    if all(isinstance(i, str) for i in idx):
        idx = from_names(idx)
    arr = np.asarray(idx)
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{field} must be a sequence of ints or of names, got {idx!r}")
    if len(set(arr.tolist())) != arr.size or arr.min() < 0:
        raise ValueError(f"{field} must be unique non-negative indices, got {idx!r}")
    if size is not None and arr.max() >= size:
        raise ValueError(f"{field} has index {arr.max()} >= number of entries {size}")
    return arr


def declared_model(engine, problem: Problem) -> Callable[[Array, Array], Array]:
    """``F(w [W], theta [P]) -> x [S]`` in float64 on the problem's declared
    parameters and outputs, unperturbed."""
    measure = measure_declared(
        lambda w, theta: engine_outputs(engine, w, theta),
        problem.theta_base,
        problem.theta_names,
        problem.output_names,
    )

    def model(w: Array, theta: Array) -> Array:
        return measure(w.astype(jnp.float64), theta.astype(jnp.float64))

    return model


def make_model(
    engine, problem: Problem, bias: Array, noise_sigma: Array, key: PRNGKey
) -> Callable[[Array, Array], Array]:
    """:func:`declared_model` perturbed as the module says."""
    clean = declared_model(engine, problem)
    std = jnp.asarray(problem.norm.x_std)

    def model(w: Array, theta: Array) -> Array:
        w, theta = w.astype(jnp.float64), theta.astype(jnp.float64)
        x = clean(w, theta)
        return perturb_output(x, evaluation_key(key, w, theta), bias, noise_sigma, std)

    return model


def model_method(engine, problem: Problem, table_cfg, name: str) -> Method:
    """A registered method on the model (its config ``table_cfg``,
    :mod:`jaxcal.calibrators.methods`) on the perturbable F, with its prior at the
    box centre and parameters scaled by the half-width."""
    # the method's calibrator on this F: the outputs in units of their training
    # std with the paper's r, the prior at the box centre
    factory = method_of(table_cfg).factory
    cfg = getattr(table_cfg, table_cfg.field_name)  # the filter's or solver's own
    inputs = inputs_of(problem, np.float64)._replace(
        x_mean=jnp.asarray(problem.norm.x_mean, jnp.float64),
        noise_std=jnp.asarray(problem.norm.x_std, jnp.float64),
        theta0=jnp.asarray(problem.theta_centre, jnp.float64),
    )

    def on(model) -> Calibrator:
        return factory(problem, table_cfg, measure=model)(inputs)

    def build(bias, noise_sigma):
        return with_step_key(
            lambda key: on(make_model(engine, problem, bias, noise_sigma, key))
        )

    info = {"model": f"F ({problem.model.name})", **dataclasses.asdict(cfg)}
    # the engine's valid inputs; a model without an envelope checks finiteness only
    envelope = getattr(engine, "envelope", None)
    check = None if envelope is None else SampleCheck(*envelope.w_box())
    return make_method(
        name, build, jnp.float64, info, check=check,
        deploy_fn=lambda: on(declared_model(engine, problem)),
    )  # fmt: skip


def paper_config(method, ukf: UKFConfig, least_squares: LeastSquaresConfig):
    """The config of a registered method on the model with the paper's settings: the
    UKF's and least squares' own, another method's with the UKF's values of the
    settings it shares (``q``, ``r``, ``prior_std``, ...: a like-for-like
    comparison)."""
    inner, field = method.config.field_type, method.config.field_name
    own = {UKFConfig: ukf, LeastSquaresConfig: least_squares}
    if inner in own:
        return method.config(**{field: own[inner]})
    names = {f.name for f in dataclasses.fields(inner)}
    paper = dataclasses.asdict(ukf)
    settings = inner(**{k: paper[k] for k in names & set(paper)})
    return method.config(**{field: settings})


# ------------------------------------------------------------------ learned


def e2e_method(
    params: E2EParams, name: str, info: dict, check: SampleCheck | None = None
) -> Method:
    """A trained E2E network; model-free, so perturbations do not apply.

    ``check``: its valid input box (the suite passes the engine's envelope).
    """

    def build(bias, noise_sigma):
        del bias, noise_sigma  # G has no model to perturb
        return make_e2e_calibrator(params)

    # deployed as scored: no model, so no noise key (``Method.deploy``'s fallback)
    return make_method(name, build, jnp.float32, info, model_free=True, check=check)


def policy_method(run, name: str) -> Method:
    """A trained policy (a :class:`jaxcal.deploy.LoadedRun`) with a perturbable D.

    The perturbation acts on x-hat_t = D(w_t, x-hat_{t-1}, theta_t), i.e. on the
    output of the simulator the policy deploys with, as in the paper; the perturbed
    x-hat is what the policy observes next.
    """
    params = run.params
    std = jnp.asarray(params.x_std)

    def build(bias, noise_sigma):
        return with_step_key(
            lambda key: make_policy_calibrator(
                run.actor,
                perturbed_dynamics(run.dynamics, key, bias, noise_sigma, std),
                params,
                run.band,
            )
        )

    # deployed: the run's own D or F, one sample per call, so a model with a
    # warm-startable solve carries it from sample to sample
    warm = isinstance(run.dynamics, HintedDynamics)

    def deploy() -> Calibrator:
        return make_policy_calibrator(
            run.actor, run.dynamics, params, run.band, warm_start=warm
        )

    info = {
        "run": str(run.run_dir),
        "checkpoint_step": run.step,
        "dynamics": run.config.dynamics,
        "seed": run.config.seed,
        "preset": run.config.preset,
    }
    dtype = jnp.float64 if run.config.dynamics == "physics" else jnp.float32
    # flags samples far outside the run's training range
    return make_method(
        name, build, dtype, info, check=run_check(run), deploy_fn=deploy, warm=warm
    )
