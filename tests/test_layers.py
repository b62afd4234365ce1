"""The package's structure: layers that import one way, private names kept private, small
files (the layer picture is in docs/contributing.md).

Read from the source with `ast`, so nothing is imported or run.
"""

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "lievi"

# Lowest first. A module may import from its own layer or any lower one, never a higher.
LAYERS = (
    ("foundations", ("_results", "_checks", "_small_linalg")),
    ("solvers", ("_newton",)),
    ("groups", ("_groups",)),
    ("physics", ("_systems", "_forcing")),
    ("kernels", ("_kernels",)),
    ("integrators", ("_integrators",)),
    (
        "step loop",
        (
            "_progress",
            "_save",
            "_solution",
            "_monitor",
            "_options",
            "_steppers",
            "_loop",
            "_simulate",
        ),
    ),
    (
        "batches",
        (
            "_simulate_batch",
            "_sharding",
            "_stream",
            "_stream_writer",
            "_stream_record",
            "_simulate_neighbors",
        ),
    ),
    (
        "applications",
        (
            "_reference",
            "advanced",
            "diagnostics",
            "_identification",
            "_fit_optimizer",
            "_optimal_control",
            "_suggest",
            "_suggest_knowledge",
            "_world",
        ),
    ),
    ("public API", ("",)),  # `lievi/__init__.py`: the names users import
    ("command line", ("_cli", "_demo", "_demo_control", "__main__")),
)
MAX_LINES = 500


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _layer(module: str) -> int | None:
    """The layer of `lievi.x.y`, from its first component (`lievi` itself: "public API")."""
    parts = module.split(".") + [""]
    for index, (_, prefixes) in enumerate(LAYERS):
        if parts[1] in prefixes:
            return index
    raise AssertionError(f"{module} is in no layer: add it to LAYERS and docs/contributing.md")


def _imports(path: pathlib.Path):
    """`(imported module, imported names)` for each `from … import …` of `lievi` modules."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "lievi":
                continue
            names = [alias.name for alias in node.names]
            if node.module is None or target.rsplit(".", 1)[-1] != node.module.rsplit(".", 1)[-1]:
                # `from . import _x`: the names are modules
                yield from ((f"{target}.{name}", []) for name in names)
            else:
                yield target, names
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "lievi":
                    yield alias.name, []


FILES = sorted(PACKAGE.rglob("*.py"))


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_run_down_the_layers(path):
    module = _module_name(path)
    own = _layer(module)
    for target, _ in _imports(path):
        other = _layer(target)
        assert other <= own, (
            f"{module} (layer {LAYERS[own][0]!r}) imports {target} (layer "
            f"{LAYERS[other][0]!r}): imports run down the layers only"
        )


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_private_name_crosses_modules(path):
    """A leading underscore means private to its file (equinox's convention): a name used
    by another module is public in its own."""
    for target, names in _imports(path):
        private = [n for n in names if n.startswith("_") and not n.startswith("__")]
        assert not private, f"{_module_name(path)} imports private {private} from {target}"


def test_no_import_cycles():
    graph = {}
    for path in FILES:
        module = _module_name(path)
        graph[module] = {t for t, _ in _imports(path) if t != module}
    # Depth-first search for a back edge (imports of a package count as its __init__).
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for child in graph.get(node, ()):
            if child == "lievi":
                continue
            if state.get(child) == "open":
                cycle = stack[stack.index(child) :] + [child]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if child not in state:
                visit(child)
        stack.pop()
        state[node] = "done"

    for node in graph:
        if node not in state:
            visit(node)


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_files_are_small(path):
    lines = len(path.read_text().splitlines())
    assert lines <= MAX_LINES, f"{path.name} has {lines} lines (at most {MAX_LINES}): split it"


def test_the_integrator_interface_names_no_concrete_system_nor_walks_classes():
    """`AbstractIntegrator` states its contract against `AbstractLieSystem` alone (the
    bodies a method steps are built by the system layer, `RigidBodies.free_flow`), and an
    integrator says which kernel it has (`own_step`, `kernels`) rather than having its
    class hierarchy inspected."""
    path = PACKAGE / "_integrators" / "_base.py"
    systems = {target for target, _ in _imports(path) if target.startswith("lievi._systems")}
    assert systems == {"lievi._systems._base"}, systems
    for source in sorted((PACKAGE / "_integrators").glob("*.py")):
        assert "__mro__" not in source.read_text(), source.name
