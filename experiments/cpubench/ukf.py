"""UKF: time per sample per unit of :mod:`jaxcal.calibrators.ukf` against filterpy and
dynamax, one unit and a vmapped fleet.

Every filter runs the same model and the same maths: the paper's random-walk state
over the scaled parameters, q = r = 0.01 on normalised outputs, 2P + 1 sigma points
with alpha = 1, beta = 2, kappa = 0 (all three libraries then place the same points:
mean +- sqrt(P) times the columns of the lower Cholesky factor), float64, and no extra
model evaluation at the posterior mean (``posterior_xhat=False``), so each step costs
2P + 1 evaluations of F in every library. The largest difference of the estimates
against ours is reported as a check that the work is the same.

Two measurement models:

* ``engine``: the C-MAPSS-like turbofan F of
  ``jaxcal.models.turbofan.physics.engine.load_engine("cmapss")`` on the declared
  parameter HPT_eff_mod (the others at 0) and the 14 measured sensors, through
  :func:`~jaxcal.paper.methods.measure_declared`; filterpy calls
  the engine's evaluate jitted for one sample. F dominates the step here.
* ``toy``: x = tanh(A theta + B w) with P = 4, S = 14, W = 4, cheap enough that the
  filters' own per-step overhead is what is measured; filterpy gets the same model in
  numpy (its natural use), the JAX filters get it in jax.numpy.

Fleet: ours and dynamax vmapped over units in one jitted call; filterpy has no batch
mode, so a fleet costs it what one unit costs, per unit-step.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from cpubench.measure import (
    blocking,
    concurrently,
    figure,
    missing_peer,
    peer,
    skipped,
    time_interleaved,
    try_import,
)
from jaxcal.calibrators.interface import Measurement
from jaxcal.calibrators.ukf import UKFConfig, ukf_filter
from jaxcal.paper.methods import measure_declared

CFG = UKFConfig(posterior_xhat=False)  # q = r = 0.01, alpha 1, beta 2, kappa 0
_DISABLED = "optional peers disabled (--no-optional-peers)"


@dataclasses.dataclass(frozen=True)
class UKFSizes:
    """Record lengths of one model's runs (filterpy's is shorter: it is slow)."""

    steps: int  # T of the single-unit runs (ours, dynamax)
    fleet_units: int  # U
    fleet_steps: int  # T of the fleet runs
    filterpy_steps: int  # T of filterpy's run
    repeats: int
    dynamax_fleet: bool = True  # dynamax vmapped too (one more compilation)
    unroll: int = 1  # lax.scan unroll of our filter (8 helps cheap steps)


TOY_SIZES = UKFSizes(2000, 100, 500, 300, repeats=5, unroll=8)
ENGINE_SIZES = UKFSizes(100, 100, 10, 30, repeats=3, dynamax_fleet=False)
QUICK_TOY_SIZES = UKFSizes(50, 4, 20, 20, repeats=2, dynamax_fleet=True, unroll=1)


@dataclasses.dataclass(frozen=True)
class Model:
    """A measurement model ``F(w, theta)`` in the forms each library wants.

    Attributes:
        name: ``toy`` or ``engine``.
        measure: jax ``(w [W], theta [P]) -> x [S]``, jittable and vmappable.
        measure_host: numpy ``(w, theta) -> x`` for filterpy.
        theta0: ``[P]`` prior mean; theta_scale: ``[P]`` scale of the filtered state.
        measurement: the outputs' centre and scale (``noise_std``; the noise std is
            ``r`` times it), the outputs compared as ``(x - centre) / noise_std``.
        sample_w: ``(rng, n) -> w [n, W]`` operating conditions.
        sample_theta: ``(rng, T) -> theta [T, P]``, a slowly drifting truth.
    """

    name: str
    measure: object
    measure_host: object
    theta0: np.ndarray
    theta_scale: np.ndarray
    measurement: Measurement
    sample_w: object
    sample_theta: object


def toy_model(seed: int = 0) -> Model:
    """x = tanh(A theta + B w), P = 4, S = 14, W = 4 (normalised outputs)."""
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(14, 4)), 0.5 * rng.normal(size=(14, 4))
    a_j, b_j = jnp.asarray(a), jnp.asarray(b)

    def measure(w, theta):
        return jnp.tanh(a_j @ theta + b_j @ w)

    def measure_host(w, theta):
        return np.tanh(a @ theta + b @ w)

    def sample_theta(rng, steps):
        return 0.3 + np.cumsum(0.01 * rng.normal(size=(steps, 4)), axis=0)

    return Model(
        "toy", measure, measure_host, np.zeros(4), np.ones(4),
        Measurement(jnp.zeros(14), jnp.ones(14)),
        lambda rng, n: rng.normal(size=(n, 4)), sample_theta,
    )  # fmt: skip


def engine_model() -> Model:
    """The ``cmapss`` engine on HPT_eff_mod and the 14 measured sensors."""
    from jaxcal.cli.bench import envelope_points
    from jaxcal.models.turbofan.physics.constants import (
        MEASURED_SENSOR_NAMES,
        health_index,
        sensor_index,
    )
    from jaxcal.models.turbofan.physics.engine import load_engine

    engine = load_engine("cmapss")
    declared, sensors = (
        health_index(["HPT_eff_mod"]),
        sensor_index(MEASURED_SENSOR_NAMES),
    )
    measure = measure_declared(
        lambda w, th: engine.evaluate(w, th)[0], np.zeros(10), declared, sensors
    )
    # filterpy's F: the engine jitted at batch 1, the very program the engine section
    # compiles (so the persistent compilation cache serves it), then the same scatter
    # of the declared parameter and the same sensor selection on the host.
    evaluate = jax.jit(engine.evaluate)

    def measure_host(w, theta):
        theta_full = np.zeros((1, 10))
        theta_full[0, declared] = theta
        return np.asarray(evaluate(np.asarray(w)[None], theta_full)[0])[0, sensors]

    # Outputs compared in units of their spread over healthy engines in the envelope
    # (a stand-in for training statistics; the noise is r = 0.01 of it): host calls
    # of the same jitted function, no extra compilation.
    rng = np.random.default_rng(7)
    w_ref, _ = envelope_points(64, seed=7)
    x_ref = np.stack([measure_host(w, np.zeros(1)) for w in w_ref])
    measurement = Measurement(jnp.asarray(x_ref.mean(0)), jnp.asarray(x_ref.std(0)))

    def sample_theta(rng, steps):
        start = rng.uniform(-0.01, -0.002)
        return np.linspace(start, start - 0.005, steps)[:, None]

    def sample_w(rng, n):
        return envelope_points(n, seed=int(rng.integers(1 << 30)))[0]

    del rng
    return Model(
        "engine", measure, measure_host, np.array([-0.008]), np.array([0.005]),
        measurement, sample_w, sample_theta,
    )  # fmt: skip


def _records(model: Model, rng, units: int, steps: int):
    """``(w [U, T, W], x [U, T, S])`` with x = F(w, theta) + N(0, (0.01 std)^2)."""
    ws, xs = [], []
    std = np.asarray(model.measurement.noise_std)
    for _ in range(units):
        w = model.sample_w(rng, steps)
        theta = model.sample_theta(rng, steps)
        pairs = zip(w, theta, strict=True)
        x = np.stack([model.measure_host(w_t, th) for w_t, th in pairs])
        ws.append(w)
        xs.append(x + 0.01 * std * rng.normal(size=x.shape))
    return np.stack(ws), np.stack(xs)


def _filterpy_runner(model: Model, w: np.ndarray, x: np.ndarray):
    """``(run, theta_of_last_run)`` for filterpy's UKF over one record."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    p, s = model.theta0.shape[0], x.shape[-1]
    scale, mean, std = (
        model.theta_scale,
        np.asarray(model.measurement.centre),
        np.asarray(model.measurement.noise_std),
    )
    out = {}

    def hx(z, w_t):
        return (model.measure_host(w_t, scale * z) - mean) / std

    def run():
        points = MerweScaledSigmaPoints(
            p, alpha=CFG.alpha, beta=CFG.beta, kappa=CFG.kappa
        )
        ukf = UnscentedKalmanFilter(p, s, 1.0, hx, lambda z, dt: z, points)
        ukf.x = model.theta0 / scale
        ukf.P = CFG.prior_std**2 * np.eye(p)
        ukf.Q = CFG.q**2 * np.eye(p)
        ukf.R = CFG.r**2 * np.eye(s)
        thetas = []
        for w_t, x_t in zip(w, x, strict=True):
            ukf.predict()
            ukf.update((x_t - mean) / std, w_t=w_t)
            thetas.append(scale * ukf.x)
        out["theta"] = np.stack(thetas)

    return run, out


def _dynamax_filter(model: Model, dynamax_ukf):
    """A jitted ``(w [T, W], x [T, S]) -> theta [T, P]`` of dynamax's UKF."""
    from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM

    p = model.theta0.shape[0]
    scale = jnp.asarray(model.theta_scale)
    s = model.measurement.centre.shape[0]
    params = ParamsNLGSSM(
        initial_mean=jnp.asarray(model.theta0) / scale,
        # dynamax conditions before it predicts: start from our first prediction.
        initial_covariance=(CFG.prior_std**2 + CFG.q**2) * jnp.eye(p),
        dynamics_function=lambda z, w: z,
        dynamics_covariance=CFG.q**2 * jnp.eye(p),
        emission_function=lambda z, w: (
            (model.measure(w, scale * z) - model.measurement.centre)
            / model.measurement.noise_std
        ),
        emission_covariance=CFG.r**2 * jnp.eye(s),
    )
    hyper = dynamax_ukf.UKFHyperParams(alpha=CFG.alpha, beta=CFG.beta, kappa=CFG.kappa)

    def run(w, x):
        x_n = (x - model.measurement.centre) / model.measurement.noise_std
        post = dynamax_ukf.unscented_kalman_filter(
            params, x_n, hyper, inputs=w, output_fields=["filtered_means"]
        )
        return scale * post.filtered_means

    return run


def _or_error(fn):
    """``fn()``, or the exception it raised (a peer's failure is reported)."""
    try:
        return fn()
    except Exception as err:
        return err


def bench_model(model: Model, sizes: UKFSizes, *, peers: bool = True) -> dict:
    """Times our UKF and the peers on one model; returns ``{"config", "figures"}``."""
    rng = np.random.default_rng(1)
    w1, x1 = (a[0] for a in _records(model, rng, 1, sizes.steps))
    wf, xf = _records(model, rng, sizes.fleet_units, sizes.fleet_steps)
    theta0, scale = jnp.asarray(model.theta0), jnp.asarray(model.theta_scale)

    def ours(w, x):
        # An explicit mask: built inside jit it would be a constant that XLA spends
        # seconds folding (a vmapped argmax over a broadcast of ones).
        return ukf_filter(
            model.measure, w, x, model.measurement, CFG, theta0=theta0,
            theta_scale=scale, mask=np.ones(w.shape[:-1], bool), unroll=sizes.unroll,
        ).theta  # fmt: skip

    agreement, reasons = {}, {}
    # Peers are imported before the concurrent warm-up: try_import restores JAX flags.
    kalman, reasons["filterpy"] = (
        try_import("filterpy.kalman") if peers else (None, _DISABLED)
    )
    dx, reasons["dynamax"] = (
        try_import("dynamax.nonlinear_gaussian_ssm.inference_ukf")
        if peers
        else (None, _DISABLED)
    )
    fns = {"ours_single": blocking(ours, w1, x1), "ours_fleet": blocking(ours, wf, xf)}
    units_steps = sizes.fleet_units * sizes.fleet_steps
    work = {"ours_single": sizes.steps, "ours_fleet": units_steps,
            "dynamax_single": sizes.steps, "dynamax_fleet": units_steps,
            "filterpy": sizes.filterpy_steps}  # fmt: skip
    warm = {
        "ours_single": lambda: np.asarray(ours(w1, x1)),
        "ours_fleet": lambda: jax.block_until_ready(ours(wf, xf)),
    }
    if dx is not None:
        try:
            dx_run = _dynamax_filter(model, dx)
            dx_single = jax.jit(dx_run)
            fns["dynamax_single"] = blocking(dx_single, w1, x1)
            warm["dynamax_single"] = lambda: _or_error(
                lambda: np.asarray(dx_single(w1, x1))
            )
            if sizes.dynamax_fleet:
                dx_fleet = jax.jit(jax.vmap(dx_run))
                fns["dynamax_fleet"] = blocking(dx_fleet, wf, xf)
                warm["dynamax_fleet"] = lambda: _or_error(fns["dynamax_fleet"])
        except Exception as err:  # a broken optional peer is reported, not fatal
            reasons["dynamax"] = f"dynamax failed: {type(err).__name__}: {err}"
    # Every program compiles side by side before any timing.
    warmed = dict(zip(warm, concurrently(*warm.values()), strict=True))
    theta_ours = warmed["ours_single"]
    for key in ("dynamax_single", "dynamax_fleet"):
        if isinstance(warmed.get(key), Exception):
            err = warmed[key]
            reasons["dynamax"] = f"dynamax failed: {type(err).__name__}: {err}"
            fns.pop("dynamax_single", None)
            fns.pop("dynamax_fleet", None)
    if "dynamax_single" in fns:
        theta_dx = warmed["dynamax_single"]
        agreement["dynamax"] = float(np.max(np.abs(theta_dx - theta_ours)))

    if kalman is not None:
        n = sizes.filterpy_steps
        try:
            run_fp, fp_out = _filterpy_runner(model, w1[:n], x1[:n])
            run_fp()
            fns["filterpy"] = run_fp
            agreement["filterpy"] = float(
                np.max(np.abs(fp_out["theta"] - theta_ours[:n]))
            )
        except Exception as err:  # a broken optional peer is reported, not fatal
            reasons["filterpy"] = f"filterpy failed: {type(err).__name__}: {err}"
    t = time_interleaved(fns, repeats=sizes.repeats, work=work)

    def peer_of(key: str, name: str, missing: str) -> dict:
        if key not in t:
            return missing_peer(name, missing)
        median, best = t[key].per_item_us()
        return peer(name, median, "us/sample/unit", best)

    fp_reason = reasons["filterpy"]
    dx_reason = reasons["dynamax"]
    dx_fleet_reason = dx_reason or "dynamax fleet not run for this model (compile cost)"
    single, single_best = t["ours_single"].per_item_us()
    fleet, fleet_best = t["ours_fleet"].per_item_us()
    unit = "us/sample/unit"
    filterpy_name = "filterpy UnscentedKalmanFilter (python loop, one unit at a time)"
    return {
        "config": {
            **dataclasses.asdict(sizes),
            "model": model.name,
            "num_params": int(model.theta0.shape[0]),
            "num_sensors": int(model.measurement.centre.shape[0]),
            "sigma_points": 2 * int(model.theta0.shape[0]) + 1,
            "max_abs_theta_diff_vs_ours": agreement,
        },
        "figures": {
            "single_vs_filterpy": figure(
                single, unit, "lower", peer_of("filterpy", filterpy_name, fp_reason),
                best=single_best,
            ),
            "single_vs_dynamax": figure(
                single, unit, "lower",
                peer_of("dynamax_single", "dynamax unscented_kalman_filter", dx_reason),
                best=single_best,
            ),
            "fleet_vs_filterpy": figure(
                fleet, unit, "lower", peer_of("filterpy", filterpy_name, fp_reason),
                best=fleet_best, units=sizes.fleet_units,
            ),
            "fleet_vs_dynamax": figure(
                fleet, unit, "lower",
                peer_of("dynamax_fleet", "dynamax unscented_kalman_filter, vmapped",
                        dx_fleet_reason),
                best=fleet_best, units=sizes.fleet_units,
            ),
        },
    }  # fmt: skip


def bench_ukf(*, quick: bool, peers: bool) -> dict:
    """The UKF section: the toy model, then (unless ``quick``) the engine.

    Returns:
        ``{"config": {"toy": ..., "engine": ...}, "figures": {"toy_<figure>": ...,
        "engine_<figure>": ...}}``.
    """
    runs = {"toy": bench_model(toy_model(), QUICK_TOY_SIZES if quick else TOY_SIZES,
                               peers=peers)}  # fmt: skip
    if not quick:
        runs["engine"] = bench_model(engine_model(), ENGINE_SIZES, peers=peers)
    config = {name: run["config"] for name, run in runs.items()}
    figures = {f"{name}_{key}": fig for name, run in runs.items()
               for key, fig in run["figures"].items()}  # fmt: skip
    if quick:
        reason = "--quick: the engine's Newton solve takes ~35 s to compile"
        config["engine"] = {"skipped": reason}
        for key in runs["toy"]["figures"]:
            figures[f"engine_{key}"] = skipped(reason)
    return {"config": config, "figures": figures}
