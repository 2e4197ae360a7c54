"""The package's import graph: one way down a fixed order of layers, no cycle, no
command line below ``jaxcal/cli/``, and a core that imports nothing of the turbofan."""

import ast
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "jaxcal"

# The documented ``python -m`` paths: shims that only forward to their cli module.
SHIMS = {
    "jaxcal.train": "jaxcal.cli.train",
    "jaxcal.evaluate": "jaxcal.cli.evaluate",
    "jaxcal.diagnose": "jaxcal.cli.diagnose",
    "jaxcal.generate": "jaxcal.cli.generate",
    "jaxcal.bench": "jaxcal.cli.bench",
    "jaxcal.prognose": "jaxcal.cli.prognose",
    "jaxcal.fleet.__main__": "jaxcal.cli.fleet",
    "jaxcal.validate.__main__": "jaxcal.cli.validate",
}

# Bottom to top. A module belongs to the layer of the longest entry that is its name or
# a package above it; it may import its own layer and the layers below, never above
# (function-level imports count). Every module must have a layer.
LAYERS = (
    # host-only leaves: types, precision, settings, caches, run-folder files, figures,
    # progress lines, the consent to run code from outside the package
    (
        "jaxcal.typedefs",
        "jaxcal.trust",
        "jaxcal.version",
        "jaxcal.precision",
        "jaxcal.settings",
        "jaxcal.cache",
        "jaxcal.numerics",
        "jaxcal.runs",
        "jaxcal.plotting",
        "jaxcal.progress",
    ),
    ("jaxcal.model_contract", "jaxcal.model_spec", "jaxcal.model"),
    ("jaxcal.data",),
    ("jaxcal.problem",),
    ("jaxcal.models",),
    ("jaxcal.nets", "jaxcal.surrogate", "jaxcal.envs", "jaxcal.agents"),
    # the policy method reads a trained run itself (calibrators.methods.policy.
    # loading): the training job's config, runner, components and model source,
    # which import nothing above, sit at its layer
    (
        "jaxcal.calibrators",
        "jaxcal.training.config",
        "jaxcal.training.config_sections",
        "jaxcal.training.runner",
        "jaxcal.training.components",
        "jaxcal.training.model_source",
    ),
    # the turbofan's training data and fleet stream sit with the layers they feed
    ("jaxcal.training", "jaxcal.models.turbofan.training"),
    ("jaxcal.deploy",),
    (
        "jaxcal.diagnosis",
        "jaxcal.fleet",
        "jaxcal.paper",
        "jaxcal.models.turbofan.fleet",
        "jaxcal.prognosis",
    ),
    # the command lines, their shims, and the package root (the public names,
    # imported lazily)
    # (jaxcal.validate: a package only so that its shim is a __main__)
    ("jaxcal.cli", *SHIMS, "jaxcal.validate", "jaxcal"),
)

# sys.argv read, not parsed: the lock file records who holds a run (pid, command).
ARGV_READERS = {"jaxcal.runs.lock"}


def _module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_package(module: str) -> bool:
    return (ROOT.parent / module.replace(".", "/")).is_dir()


def _imports(module: str, tree: ast.AST, modules: set[str]) -> set[str]:
    """jaxcal modules imported anywhere in the file (function-level imports too); a
    ``from package import name`` counts as the submodule when ``name`` is one, else as
    the package."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against this module's package
                package = module.split(".")
                package = package if _is_package(module) else package[:-1]
                package = package[: len(package) - node.level + 1]
                base = ".".join([*package, base] if base else package)
            subs = [f"{base}.{a.name}" for a in node.names]
            names = [s for s in subs if s in modules]
            if len(names) < len(subs):
                names.append(base)
        else:
            continue
        found |= {n for n in names if n in modules}
    return found - {module}


@pytest.fixture(scope="module")
def trees():
    return {_module_name(p): ast.parse(p.read_text()) for p in ROOT.rglob("*.py")}


@pytest.fixture(scope="module")
def graph(trees):
    modules = set(trees)
    return {m: _imports(m, tree, modules) for m, tree in trees.items()}


def _layer(module: str) -> int | None:
    best = None  # (length of the matching entry, layer)
    for index, entries in enumerate(LAYERS):
        for entry in entries:
            matches = module == entry or (
                entry != "jaxcal" and module.startswith(entry + ".")
            )
            if matches and (best is None or len(entry) > best[0]):
                best = (len(entry), index)
    return None if best is None else best[1]


def test_every_module_has_a_layer(graph):
    assert not sorted(m for m in graph if _layer(m) is None)


def test_no_import_runs_back_up(graph):
    offenders = {
        m: sorted(d for d in deps if _layer(d) > _layer(m))
        for m, deps in graph.items()
        if any(_layer(d) > _layer(m) for d in deps)
    }
    assert not offenders, offenders


def test_the_import_graph_has_no_cycle(graph):
    # package __init__ files re-export their children; a child importing a sibling
    # through the package is not a cycle of concepts, so packages are left out.
    packages = {m for m in graph if _is_package(m)}
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


def _is_cli(module: str) -> bool:
    return module == "jaxcal.cli" or module.startswith("jaxcal.cli.")


def _command_line_traits(module: str, tree: ast.AST) -> list[str]:
    """What makes a module a command line: a ``main``, argparse, ``sys.argv``, an
    ``if __name__ == "__main__"`` block, an import of :mod:`jaxcal.cli`."""
    traits = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and (
            node.name == "main"
        ):
            traits.append("defines main")
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names = [a.name for a in node.names]
            names += [node.module] if isinstance(node, ast.ImportFrom) else []
            if any(n and n.split(".")[0] == "argparse" for n in names):
                traits.append("imports argparse")
            if any(n and _is_cli(n) for n in names):
                traits.append("imports jaxcal.cli")
            if (
                isinstance(node, ast.ImportFrom)
                and node.module == "jaxcal"
                and ("cli" in names)
            ):
                traits.append("imports jaxcal.cli")
        elif (
            isinstance(node, ast.Attribute)
            and node.attr == "argv"
            and isinstance(node.value, ast.Name)
            and node.value.id == "sys"
            and module not in ARGV_READERS
        ):
            traits.append("uses sys.argv")
        elif (
            isinstance(node, ast.Compare)
            and isinstance(node.left, ast.Name)
            and node.left.id == "__name__"
        ):
            traits.append('has an if __name__ == "__main__" block')
    return sorted(set(traits))


def test_no_command_line_below_cli(trees):
    offenders = {
        m: traits
        for m, tree in trees.items()
        if not _is_cli(m)
        and m not in SHIMS
        and (traits := _command_line_traits(m, tree))
    }
    assert not offenders, offenders


def test_the_shims_only_forward_to_the_command_lines(trees, graph):
    for shim, target in SHIMS.items():
        body = trees[shim].body
        docstring = body[0]
        assert isinstance(docstring, ast.Expr), shim
        assert isinstance(docstring.value, ast.Constant), shim
        imported, guard = body[1:]
        assert isinstance(imported, ast.ImportFrom), shim
        assert imported.module == target, shim
        assert [a.name for a in imported.names] == ["main"], shim
        assert isinstance(guard, ast.If) and ast.unparse(guard) == (
            "if __name__ == '__main__':\n    raise SystemExit(main())"
        ), shim
        assert graph[shim] == {target}, shim


def _enables_x64_globally(tree: ast.AST) -> bool:
    """A call of ``jaxcal.precision.enable_x64()`` or ``jax.config.update(
    "jax_enable_x64", ...)``; the scoped ``with jax.enable_x64(...)`` is allowed."""
    for node in ast.walk(tree):
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


def test_no_library_module_enables_float64(trees):
    offenders = [
        m
        for m, tree in trees.items()
        if not _is_cli(m) and m != "jaxcal.precision" and _enables_x64_globally(tree)
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


def test_no_module_imports_back_the_package_that_imports_it(graph):
    # the cycle test leaves packages out (an __init__ re-exporting its children);
    # a child that takes a name defined in its own package's __init__, which in
    # turn imports the child, is a cycle all the same (hidden behind a lazy import)
    packages = {m for m in graph if _is_package(m)}
    loops = sorted(
        (p, child)
        for p in packages
        for child in graph[p]
        if child.startswith(p + ".") and p in graph.get(child, ())
    )
    assert not loops, loops


# The core: everything that calibrates any model. It imports nothing of the turbofan,
# at module level or in a function (nor names its modules for importlib): the
# registry (jaxcal.models, which names the turbofan's files), the paper, the command
# lines with their shims and the package root sit above it and may.
CORE = (
    # the model protocol, the one problem and the host-only leaves
    "jaxcal.model", "jaxcal.model_contract", "jaxcal.model_spec", "jaxcal.problem",
    "jaxcal.typedefs", "jaxcal.version", "jaxcal.precision", "jaxcal.settings",
    "jaxcal.cache", "jaxcal.trust", "jaxcal.progress", "jaxcal.plotting",
    "jaxcal.numerics", "jaxcal.runs",
    # the data container and generic readers, the calibrators, the policy's learning,
    # a trained run, the diagnosis, the fleet and the prognosis
    "jaxcal.data", "jaxcal.calibrators", "jaxcal.nets", "jaxcal.surrogate",
    "jaxcal.envs", "jaxcal.agents", "jaxcal.training", "jaxcal.deploy",
    "jaxcal.diagnosis", "jaxcal.fleet", "jaxcal.prognosis",
)  # fmt: skip
ABOVE_THE_CORE = ("jaxcal.models", "jaxcal.paper", "jaxcal.cli", "jaxcal.validate")
TURBOFAN = "jaxcal.models.turbofan"
_TURBOFAN_PATH = re.compile(r"jaxcal\.models\.turbofan(\.\w+)*")


def _in(module: str, entries) -> bool:
    return any(module == e or module.startswith(e + ".") for e in entries)


def _is_core(module: str) -> bool:
    return _in(module, CORE) and module not in SHIMS  # jaxcal.fleet.__main__: a shim


def _turbofan_imports(module: str, tree: ast.AST) -> list[str]:
    """The turbofan modules ``tree`` (the module ``module``) imports anywhere, or
    names in a string (``importlib.import_module("jaxcal.models.turbofan...")``)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against this module's package
                package = module.split(".")[: -node.level]
                base = ".".join([*package, base] if base else package)
            found |= {base} | {f"{base}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            found |= {node.value} if _TURBOFAN_PATH.fullmatch(node.value) else set()
    return sorted(n for n in found if n == TURBOFAN or n.startswith(TURBOFAN + "."))


def test_every_module_is_core_or_above_it(trees):
    above = (*ABOVE_THE_CORE, *SHIMS)
    unplaced = [m for m in trees if m != "jaxcal" and not _in(m, (*CORE, *above))]
    assert not unplaced, unplaced
    assert not [m for m in trees if _is_core(m) and _in(m, above)]


def test_the_core_imports_nothing_of_the_turbofan(trees):
    offenders = {
        m: found
        for m, tree in trees.items()
        if _is_core(m) and (found := _turbofan_imports(m, tree))
    }
    assert not offenders, offenders


@pytest.mark.parametrize(
    "source",
    [
        "import jaxcal.models.turbofan.physics.engine",
        "from jaxcal.models.turbofan.model import is_turbofan",
        "from jaxcal.models import turbofan",
        "def f():\n    from jaxcal.models.turbofan.physics import constants",
        "from ..models.turbofan.data import datasets",
        "import importlib\nimportlib.import_module('jaxcal.models.turbofan.training')",
    ],
)
def test_the_turbofan_check_finds_every_form_of_import(source):
    assert _turbofan_imports("jaxcal.data.readers", ast.parse(source))


def test_the_turbofan_check_lets_the_registry_and_prose_pass():
    source = (
        '"""Reads :mod:`jaxcal.models.turbofan.training` files."""\n'
        "import jaxcal.models.extended\nfrom jaxcal.models import load\n"
        "def f():\n    from jaxcal import models\n    return models.load('cmapss')\n"
    )
    assert not _turbofan_imports("jaxcal.data.readers", ast.parse(source))
