"""F's bits are unchanged by the speed work; the warm-started path agrees with F and
falls back to the full solve when its hint is useless."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.model import Model
from jaxcal.models.turbofan.physics import solver
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.engine import load_engine

FIXTURE = Path(__file__).parents[3] / "fixtures" / "engine_f_bits.npz"


@pytest.fixture(scope="module")
def engine():
    with jax.enable_x64(True):
        yield load_engine("cmapss")


@pytest.fixture(scope="module")
def fns(engine):
    """The jitted single-sample cold and hinted evaluations (compiled once here)."""
    return jax.jit(engine.evaluate), jax.jit(engine.evaluate_hinted)


def _stream(n=12):
    """A climbing flight segment: smoothly varying conditions, as in the data."""
    alt = np.linspace(10000.0, 16000.0, n)
    mach = np.linspace(0.39, 0.52, n)
    tra = 80.0 + 0.4 * np.sin(np.arange(n))
    t2 = np.asarray(isa_total_temperature(alt, mach))
    return np.stack([alt, mach, tra, t2], 1), np.full((n, 10), -0.004)


def test_f_bits_unchanged(engine):
    # written by the engine before the speed work (jitted, the engine closed over):
    # the paper's numbers depend on F, so any change of F must be deliberate. Equal
    # to a few ulps, not bit for bit: another CPU or XLA release may fuse and
    # vectorise the same program differently (seen: 4.6e-14 relative on a new
    # machine), while any change of F's equations moves it by far more.
    ref = np.load(FIXTURE)
    with jax.enable_x64(True):
        x, info = jax.jit(lambda w, th: engine.evaluate(w, th))(ref["w"], ref["theta"])
    np.testing.assert_allclose(np.asarray(x), ref["x"], rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.asarray(info.z), ref["z"], rtol=1e-12, atol=1e-14)


def test_hinted_stream_matches_cold(engine, fns):
    w, theta = _stream()
    cold, step = fns
    with jax.enable_x64(True):
        hint = engine.initial_hint()
        iters = []
        for t in range(len(w)):
            x, info, hint = step(w[t], theta[t], hint)
            assert bool(info.converged) and bool(hint.ok)
            x_cold = np.asarray(cold(w[t], theta[t])[0])
            np.testing.assert_allclose(np.asarray(x), x_cold, rtol=1e-8)
            iters.append(int(info.iterations))
    # after the first (cold) sample the warm path closes in a few Broyden steps and
    # to the solver's own tolerance
    assert max(iters[1:]) < 10
    assert float(info.residual_norm) <= solver.SolverConfig().tol


def _exact_jinv(engine, w, theta, z):
    from jaxcal.models.turbofan.physics import cycle
    from jaxcal.models.turbofan.physics.evaluation import residual_fn

    params = (engine.design, engine.point, w, theta, jnp.zeros(cycle.NUM_EFFECTS))
    return np.linalg.inv(np.asarray(jax.jacfwd(residual_fn)(z, params)))


@pytest.mark.parametrize("kind", ["nan", "far"])
def test_bad_hint_falls_back_to_full_solve(engine, fns, kind):
    w, theta = _stream(2)
    cruise = np.array(
        [35000.0, 0.78, 85.0, float(isa_total_temperature(35000.0, 0.78))]
    )
    cold, step = fns
    with jax.enable_x64(True):
        _, _, hint = step(w[0], theta[0], engine.initial_hint())
        if kind == "nan":
            hint = hint._replace(z=hint.z.at[3].set(jnp.nan))
        else:  # a hint of a far operating point, and a wrong sensitivity
            _, _, hint = step(cruise, theta[0], hint)
            hint = hint._replace(dz_dp=jnp.zeros_like(hint.dz_dp), p=hint.p * 0.0)
        x, info, nxt = step(w[1], theta[1], hint)
        x_cold, info_cold = cold(w[1], theta[1])
        exact = _exact_jinv(engine, w[1], theta[1], nxt.z)
    assert bool(info.converged) and np.isfinite(np.asarray(x)).all()
    np.testing.assert_allclose(np.asarray(x), np.asarray(x_cold), rtol=1e-10)
    # the fallback's signature: the next hint carries the exact inverse Jacobian
    # (a Broyden step would have carried its rank-one update instead)
    np.testing.assert_allclose(np.asarray(nxt.jinv), exact, rtol=1e-8, atol=1e-10)
    assert int(info.iterations) == int(info_cold.iterations)


def test_model_without_hint_passes_it_through():
    model = Model.from_function(
        lambda w, th: w * th[0], conditions=("a",), parameters={"p": (1.0, 0.0, 2.0)},
        outputs=("y",),
    )  # fmt: skip
    assert not model.has_hint and model.initial_hint() is None
    x, info, hint = model.evaluate_hinted(jnp.ones(1), jnp.ones(1), "anything")
    assert hint == "anything" and bool(info.valid) and float(x[0]) == 1.0
    with pytest.raises(ValueError, match="give both or none"):
        Model.from_function(
            lambda w, th: w, conditions=("a",), parameters={"p": (1.0, 0.0, 2.0)},
            outputs=("y",), hinted_fn=lambda w, th, h: (w, None, h),
        )  # fmt: skip


def test_turbofan_model_restrict_hinted(engine, fns):
    from jaxcal.models.turbofan.model import load_turbofan
    from jaxcal.models.turbofan.physics.constants import SENSOR_NAMES

    w, theta = _stream(3)
    cold, _ = fns
    used = [SENSOR_NAMES.index(n) for n in ("T50", "Nc")]
    with jax.enable_x64(True):
        model = load_turbofan("cmapss")
        assert model.has_hint
        hinted = jax.jit(model.restrict_hinted(["HPT_eff_mod"], ["T50", "Nc"]))
        hint = model.initial_hint()
        for t in range(3):
            x, hint = hinted(w[t], jnp.asarray([-0.004]), hint)
            full = np.zeros(10)
            full[6] = -0.004
            x_cold = np.asarray(cold(w[t], full)[0])[used]
            np.testing.assert_allclose(np.asarray(x), x_cold, rtol=1e-9)


def test_physics_dynamics_of_the_turbofan_carry_the_hint(engine, fns):
    # the training pipeline's physics transition is hinted for deployment streams and
    # plain (the cold F) when called as the training environment calls it
    from jaxcal.envs.memory import HintedDynamics
    from jaxcal.models.turbofan.model import load_turbofan
    from jaxcal.training.components import _dynamics

    w, theta = _stream(4)
    names = ["HPT_eff_mod"]
    with jax.enable_x64(True):
        model = load_turbofan("cmapss")
        dyn = _dynamics("physics", model, names, ["T50", "Nc"], model.nominal, None)
        assert isinstance(dyn, HintedDynamics)
        step, plain = jax.jit(dyn.step), jax.jit(dyn.plain)
        hint, xhat = dyn.init_hint(), jnp.zeros(2)
        for t in range(4):
            th = jnp.asarray(theta[t, 6:7])
            hint, x = step(None, hint, w[t], xhat, th)
            np.testing.assert_allclose(
                np.asarray(x), np.asarray(plain(None, w[t], xhat, th)), rtol=1e-9
            )
            assert bool(hint.ok)
