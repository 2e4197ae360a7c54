"""The method registry: every method is one package's ``METHOD``, and the front door,
the fleet and the paper read it instead of testing a method's name or config type."""

import ast
import dataclasses
import pathlib

import numpy as np
import pytest

from jaxcal.calibrators import methods
from jaxcal.calibrators.methods import PACKAGES, REGISTRY, Method

ROOT = pathlib.Path(__file__).resolve().parents[2] / "jaxcal"
# the callers of the registry: none may dispatch on a method's name or config type
CALLERS = (
    "calibrators/front",
    "calibrators/uncertainty/misfit_check.py",
    "fleet",
    "cli/fleet.py",
    "paper",
)


def _caller_trees():
    for entry in CALLERS:
        path = ROOT / entry
        for file in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            yield file, ast.parse(file.read_text())


def _dispatches(tree: ast.AST) -> list[str]:
    """``isinstance(..., <a method's config>)`` and ``<x> == "<a method's name>"``
    (or ``in``/``!=`` a tuple of names) in ``tree``."""
    configs = {m.config.__name__ for m in REGISTRY.values()}
    names = set(REGISTRY)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "isinstance":
            types = node.args[1]
            elts = types.elts if isinstance(types, ast.Tuple) else [types]
            hit = {getattr(e, "id", getattr(e, "attr", "")) for e in elts} & configs
            found += (
                [f"line {node.lineno}: isinstance(.., {sorted(hit)})"] if hit else []
            )
        if isinstance(node, ast.Compare):
            consts = [
                c.value
                for side in node.comparators
                for c in ([side] if not isinstance(side, ast.Tuple) else side.elts)
                if isinstance(c, ast.Constant)
            ]
            hit = {c for c in consts if isinstance(c, str)} & names
            found += [f"line {node.lineno}: compares to {sorted(hit)}"] if hit else []
    return found


def test_no_caller_dispatches_on_a_method_name_or_type():
    bad = {
        str(file.relative_to(ROOT)): hits
        for file, tree in _caller_trees()
        if (hits := _dispatches(tree))
    }
    assert not bad, f"dispatch outside the registry: {bad}"


def test_the_scan_sees_a_dispatch():  # the test above could not pass vacuously
    tree = ast.parse('if isinstance(cfg, (UKF, Policy)) or method == "ukf": pass')
    assert len(_dispatches(tree)) == 2


def test_every_package_exports_one_method_with_a_frozen_config():
    assert tuple(REGISTRY) == PACKAGES
    for name, method in REGISTRY.items():
        assert isinstance(method, Method) and method.name == name
        cfg = methods.config(name, {})  # every option has a default
        assert type(cfg) is method.config and methods.method_of(cfg) is method
        hash(cfg)  # keys the compiled programs
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(cfg, dataclasses.fields(cfg)[0].name, None)
        assert method.label


def test_an_unknown_method_lists_the_registered_ones():
    with pytest.raises(ValueError, match="must be one of .*'ukf'.*got 'kalman'"):
        methods.get("kalman")


def test_a_method_added_to_the_registry_runs_through_the_front_door(monkeypatch):
    """A method the callers have never seen (the UKF's machinery under another
    name and config) is calibrated through ``jaxcal.calibrate`` once registered."""
    import jax.numpy as jnp
    import pandas as pd

    import jaxcal
    from jaxcal.calibrators.methods.ukf import METHOD as UKF_METHOD

    @dataclasses.dataclass(frozen=True)
    class Other(UKF_METHOD.config):
        name = "other"

    other = dataclasses.replace(UKF_METHOD, name="other", config=Other, label="O")
    monkeypatch.setitem(REGISTRY, "other", other)

    def model(w, theta):
        return jnp.stack([theta[0] * w[0], theta[0] + theta[1] * w[0]])

    rng = np.random.default_rng(0)
    w = rng.uniform(0.5, 1.5, 200)
    x = np.stack([0.4 * w, 0.4 + 0.7 * w], 1) + 0.01 * rng.standard_normal((200, 2))
    box = (0.5, 0.0, 1.0)  # nominal, low, high
    m = jaxcal.Model.from_function(
        model, conditions=["w"], parameters={"a": box, "b": box}, outputs=["x1", "x2"]
    )
    data = pd.DataFrame({"unit": np.zeros(200, int), "time": np.arange(200), "w": w,
                         "x1": x[:, 0], "x2": x[:, 1]})  # fmt: skip
    got = jaxcal.calibrate(m, data, method="other", noise=0.01, progress=False)
    ref = jaxcal.calibrate(m, data, method="ukf", noise=0.01, progress=False)
    assert got.method == "other"
    np.testing.assert_allclose(got.theta, ref.theta, rtol=1e-6, atol=1e-9)
    assert abs(got.theta[-1, 0] - 0.4) < 0.02 and abs(got.theta[-1, 1] - 0.7) < 0.02
