"""A user model's digest names what it computes: same jaxpr and constants, same
digest; anything else, another digest or none."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal
from jaxcal.calibrators.programs.traced_key import traced_key


def _model(fn, **kw):
    return jaxcal.Model.from_function(
        fn, conditions=["u"], parameters={"a": (1.0, 0.5, 2.0), "b": (0.0, -1.0, 1.0)},
        outputs=["y", "z"], **kw,
    )  # fmt: skip


def _affine(scale=2.0, table=np.array([1.0, 2.0])):
    def fn(w, theta):
        return jnp.stack([theta[0] * w[0] * scale, theta[1] + jnp.sum(table) * w[0]])

    return fn


def _key(fn, dtype=jnp.float32, **kw):
    return traced_key(_model(fn, **kw), dtype)


def test_the_same_computation_has_the_same_digest_whatever_its_python_object():
    first = _key(_affine())
    assert first is not None and first.startswith("traced:")
    assert _key(_affine()) == first  # a new function object, the same program
    assert _key(_affine(), jnp.float64) != first  # another float type


@pytest.mark.parametrize(
    "changed",
    [
        lambda: _affine(scale=2.5),  # a captured Python number
        lambda: _affine(table=np.array([1.0, 2.5])),  # a captured array's value
        lambda: lambda w, th: jnp.stack([th[0] * w[0], th[1] - w[0]]),  # the code
    ],
)
def test_a_changed_number_or_line_changes_the_digest(changed):
    assert _key(changed()) != _key(_affine())


def test_a_changed_declaration_or_check_changes_the_digest():
    assert _key(_affine(), condition_range=([0.0], [1.0])) != _key(_affine())
    assert _key(_affine(), input_check=lambda w: w[0] > 0) != _key(_affine())


def test_a_changed_solver_start_changes_the_digest():
    """The diagnosis's kept programs call a model's ``warm_fn``: a model that
    differs only there must not load another's program."""

    def warm(shift):
        def fn(w, theta, e, z0):
            del e
            return _affine()(w, theta), True, jnp.nan_to_num(z0) + shift

        return fn

    one = _key(_affine(), warm_fn=warm(1.0), warm_size=2)
    assert one is not None and one != _key(_affine())
    assert _key(_affine(), warm_fn=warm(1.0), warm_size=2) == one
    assert _key(_affine(), warm_fn=warm(2.0), warm_size=2) != one


def test_a_custom_derivative_rule_is_read_through_the_traced_derivative():
    def with_rule(slope):
        @jax.custom_jvp
        def soft(v):
            return jnp.tanh(v)

        soft.defjvp(lambda p, t: (soft(p[0]), slope * t[0]))
        return lambda w, th: jnp.stack([soft(th[0] * w[0]), th[1]])

    # the primal jaxprs are equal; only the rule differs
    assert _key(with_rule(1.0)) != _key(with_rule(2.0))
    assert _key(with_rule(1.0)) == _key(with_rule(1.0))


def test_behaviour_a_jaxpr_does_not_show_gets_no_digest():
    def callback(w, th):
        y = jax.pure_callback(
            lambda v: np.asarray(v) * 2, jax.ShapeDtypeStruct((), w.dtype), w[0]
        )
        return jnp.stack([th[0] * y, th[1]])

    @jax.custom_vjp
    def twice(v):
        return 2 * v

    twice.defvjp(lambda v: (2 * v, None), lambda _, g: (2 * g,))
    assert _key(callback) is None
    assert _key(lambda w, th: jnp.stack([twice(th[0]) * w[0], th[1]])) is None
    assert _key(lambda w, th: jnp.stack([float(th[0]) * w[0], th[1]])) is None
