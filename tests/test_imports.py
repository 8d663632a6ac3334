"""casmag's modules import one another without a cycle: every import counts, at the top of a
module, inside a function or under ``if TYPE_CHECKING``, so a cycle cannot hide behind a
function-level import."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "casmag"


def module_names(root: Path) -> dict[str, Path]:
    """Dotted name of every module under root (a package folder): ``pkg.sub.mod``; a
    package's ``__init__.py`` is the package itself."""
    names = {}
    for path in sorted(root.rglob("*.py")):
        parts = [root.name, *path.relative_to(root).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts.pop()
        names[".".join(parts)] = path
    return names


def _targets(node: ast.AST, here: str, is_package: bool, modules: set[str]) -> set[str]:
    """The package's modules one import statement reaches."""
    if isinstance(node, ast.Import):
        found = set()
        for alias in node.names:
            name = alias.name
            while name and name not in modules:  # import pkg.a.b reaches pkg.a.b (or pkg.a)
                name = name.rpartition(".")[0]
            if name:
                found.add(name)
        return found
    assert isinstance(node, ast.ImportFrom)
    if node.level:
        base = here if is_package else here.rpartition(".")[0]
        for _ in range(node.level - 1):
            base = base.rpartition(".")[0]
        source = f"{base}.{node.module}" if node.module else base
    else:
        source = node.module or ""
    if source not in modules:
        return set()
    found = set()
    for alias in node.names:
        sub = f"{source}.{alias.name}"
        found.add(sub if sub in modules else source)  # from pkg import module | name
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports, wherever in the module the import is."""
    names = module_names(root)
    modules = set(names)
    graph: dict[str, set[str]] = {}
    for name, path in names.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        is_package = path.name == "__init__.py"
        edges: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                edges |= _targets(node, name, is_package, modules)
        edges.discard(name)
        graph[name] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a path that ends where it starts, or None (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)) is not None:
                return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)) is not None:
            return cycle
    return None


def test_casmag_has_no_import_cycle():
    graph = import_graph(PACKAGE)
    assert len(graph) > 30, sorted(graph)  # the package was found and read
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_a_cycle_behind_a_function_level_import_is_found(tmp_path):
    pkg = tmp_path / "pkg"
    _write(
        pkg,
        {
            "__init__.py": "",
            "a.py": "from pkg.b import g\n",
            "b.py": "def g():\n    from pkg import a\n    return a\n",
            "c.py": "from pkg.a import g\n",
        },
    )
    assert find_cycle(import_graph(pkg)) in (
        ["pkg.a", "pkg.b", "pkg.a"],
        ["pkg.b", "pkg.a", "pkg.b"],
    )


def test_cycles_through_type_checking_relative_and_subpackage_imports_are_found(tmp_path):
    pkg = tmp_path / "pkg"
    _write(
        pkg,
        {
            "__init__.py": "",
            "result.py": "from .plot import draw\n",
            "plot.py": (
                "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                "    from pkg.result import Result\n"
            ),
            "model/__init__.py": "",
            "model/motion.py": "from ..model import field\n",
            "model/field.py": "import pkg.model.motion\n",
        },
    )
    graph = import_graph(pkg)
    assert graph["pkg.result"] == {"pkg.plot"}
    assert graph["pkg.plot"] == {"pkg.result"}
    assert graph["pkg.model.motion"] == {"pkg.model.field"}
    assert graph["pkg.model.field"] == {"pkg.model.motion"}
    assert find_cycle(graph) is not None
    (pkg / "plot.py").write_text("def draw(result):\n    return result\n")
    (pkg / "model/field.py").write_text("X = 1\n")
    assert find_cycle(import_graph(pkg)) is None


def test_no_test_module_imports_another():
    """Shared helpers live in conftest.py and the helper modules (small_problems,
    problem_files), never in a test module another test file imports."""
    tests = Path(__file__).resolve().parent
    test_modules = {p.stem for p in tests.rglob("test_*.py")}
    assert len(test_modules) > 40, sorted(test_modules)  # the subfolders were read
    offenders = []
    for path in sorted(tests.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            offenders += [f"{path.name}: {n}" for n in names if n.split(".")[0] in test_modules]
    assert offenders == []


def test_tests_mirror_the_package():
    """Each test module sits in the folder of the casmag subpackage it tests (tests/model
    for casmag/model, ...); only tests of the package as a whole sit at the top."""
    tests = Path(__file__).resolve().parent
    folders = {p.parent.name for p in tests.rglob("test_*.py") if p.parent != tests}
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    assert folders <= packages, sorted(folders - packages)
    assert not list(tests.rglob("__init__.py"))  # test modules are found by their own name


#: The pipeline's layers, first to last: a module imports only from its own layer or an
#: earlier one (casmag's top-level modules, such as errors and strapdown, are the base).
#: gp comes before data because the simulations draw fields from the GP and the clock
#: search uses its likelihood; result before solver because the solvers build a Result;
#: report reads the experiments' sweep manifests.
LAYERS = ("problem", "gp", "data", "nlp", "model", "result", "solver", "experiments", "report")
#: The command line, the API reference writer and the package's public API may import anything.
TOP = ("cli", "apidocs", "casmag")


def _layer(module: str) -> int:
    parts = module.split(".")
    if module == "casmag" or parts[1] in TOP:
        return len(LAYERS) + 1
    return LAYERS.index(parts[1]) + 1 if parts[1] in LAYERS else 0


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """Imports that run back up the pipeline (a later layer imported by an earlier one)."""
    return sorted(
        f"{src} -> {dst}"
        for src, dsts in graph.items()
        for dst in dsts
        if _layer(dst) > _layer(src) and not (dst == "casmag" and _layer(src) >= 8)
    )


def test_imports_follow_the_pipeline():
    """problem -> gp -> data -> nlp -> model -> result -> solver -> experiments -> report:
    the model layer never imports a solve strategy, the problem layer never a data module."""
    assert layer_violations(import_graph(PACKAGE)) == []


def test_an_import_back_up_the_pipeline_is_found():
    graph = {"casmag.model.imu": {"casmag.solver.windowing"}, "casmag.solver.api": {"casmag.nlp"}}
    assert layer_violations(graph) == ["casmag.model.imu -> casmag.solver.windowing"]
