"""The package's import graph: one way, no cycle, no library module importing a CLI."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "jaxcal"
# Command-line mains (and their shared front); nothing below them may import them.
CLI_MODULES = {
    "jaxcal.train",
    "jaxcal.evaluate",
    "jaxcal.diagnose",
    "jaxcal.generate",
    "jaxcal.bench",
    "jaxcal.cli_args",
    "jaxcal.fleet.__main__",
    "jaxcal.physics.validate",
}


def _module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: pathlib.Path, modules: set[str]) -> set[str]:
    """jaxcal modules imported anywhere in the file (function-level imports too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        found |= {n for n in names if n in modules}
    return found


@pytest.fixture(scope="module")
def graph():
    files = {_module_name(p): p for p in ROOT.rglob("*.py")}
    modules = set(files)
    return {m: _imports(p, modules) - {m} for m, p in files.items()}


def test_no_library_module_imports_a_command_line_module(graph):
    offenders = {
        m: sorted(deps & CLI_MODULES)
        for m, deps in graph.items()
        if m not in CLI_MODULES and deps & CLI_MODULES
    }
    assert not offenders, offenders


def test_the_import_graph_has_no_cycle(graph):
    # package __init__ files re-export their children; a child importing a sibling
    # through the package is not a cycle of concepts, so packages are left out.
    packages = {m for m in graph if (ROOT.parent / m.replace(".", "/")).is_dir()}
    edges = {m: deps - packages for m, deps in graph.items() if m not in packages}
    state, cycle = {}, []

    def visit(node, stack):
        state[node] = "open"
        for dep in sorted(edges.get(node, ())):
            if state.get(dep) == "open":
                cycle.append(stack[stack.index(dep) :] + [dep])
            elif dep not in state:
                visit(dep, stack + [dep])
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    assert not cycle, cycle[:3]


def _enables_x64_globally(path: pathlib.Path) -> bool:
    """A call of ``jaxcal.precision.enable_x64()`` or ``jax.config.update(
    "jax_enable_x64", ...)``; the scoped ``with jax.enable_x64(...)`` is allowed."""
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Name) and func.id == "enable_x64":
            return True
        if isinstance(func, ast.Attribute) and func.attr == "enable_x64":
            if not (isinstance(func.value, ast.Name) and func.value.id == "jax"):
                return True
        if isinstance(func, ast.Attribute) and func.attr == "update" and node.args:
            first = node.args[0]
            if isinstance(first, ast.Constant) and first.value == "jax_enable_x64":
                return True
    return False


def test_no_library_module_enables_float64():
    offenders = [
        _module_name(p)
        for p in ROOT.rglob("*.py")
        if _module_name(p) not in CLI_MODULES | {"jaxcal.precision"}
        and _enables_x64_globally(p)
    ]
    assert not offenders, offenders


def test_the_numerical_cores_sit_at_the_bottom_of_the_graph(graph):
    """``jaxcal.numerics`` (the one least-squares core) imports no jaxcal module but
    the type aliases, so every layer may use it without an arrow running back up."""
    allowed = {"jaxcal.typedefs"}
    offenders = {
        m: sorted(deps - allowed)
        for m, deps in graph.items()
        if m.startswith("jaxcal.numerics") and deps - allowed
    }
    assert not offenders, offenders
