"""The package's import graph, read from the source with `ast` (nothing is imported): no module imports
itself through others, the model depends on nothing but itself, the config and the dataset format, and
only `gns_bench/tracking.py` talks to MLflow.

Every import counts, at the top of a module or inside a function: a lazy import hides a loop from Python,
not from the reader.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = "gns_bench"
PACKAGE_DIR = Path(__file__).resolve().parents[1] / PACKAGE
MODEL = f"{PACKAGE}.model"
MODEL_MAY_IMPORT = {f"{PACKAGE}.config", f"{PACKAGE}.data.format"}  # the config, the dataset's metadata type
MLFLOW_MODULE = f"{PACKAGE}.tracking"

Edge = tuple[str, str]  # (importer, imported)


def find_modules(package_dir: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package (`pkg/__init__.py` is `pkg`)."""
    modules = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = path.relative_to(package_dir.parent).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _existing(name: str, modules: dict[str, Path]) -> str | None:
    """The module `name` names, or its nearest enclosing module that exists."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> tuple[dict[str, int], dict[str, int]]:
    """What the module imports: (package modules, other top-level packages), each -> the first line doing so.

    `from a.b import c` is module `a.b.c` when that is a module, else `a.b`; relative imports are resolved
    against the importing module's package."""
    internal: dict[str, int] = {}
    external: dict[str, int] = {}
    top = name.split(".")[0]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]

    def add(target: str, line: int) -> None:
        if target.split(".")[0] == top:
            resolved = _existing(target, modules)
            if resolved is not None and resolved != name:
                internal[resolved] = min(line, internal.get(resolved, line))
        else:
            external[target.split(".")[0]] = min(line, external.get(target.split(".")[0], line))

    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name, node.lineno)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            for alias in node.names:
                candidate = f"{base}.{alias.name}"
                add(candidate if candidate in modules else base, node.lineno)
    return internal, external


def import_graph(package_dir: Path) -> tuple[dict[Edge, int], dict[str, dict[str, int]]]:
    """({(importer, imported): line} between the package's modules, {module: {external package: line}})."""
    modules = find_modules(package_dir)
    edges: dict[Edge, int] = {}
    external: dict[str, dict[str, int]] = {}
    for name, path in modules.items():
        internal, external[name] = imports_of(name, path, modules)
        edges.update({(name, target): line for target, line in internal.items()})
    return edges, external


def cycles(edges: dict[Edge, int]) -> list[tuple[list[str], list[str]]]:
    """Each group of modules that import one another (a strongly connected component), with its shortest
    loop through the group's first module (that module repeated at the end)."""
    graph: dict[str, list[str]] = {}
    for a, b in sorted(edges):
        graph.setdefault(a, []).append(b)
        graph.setdefault(b, [])
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def connect(node: str) -> None:  # Tarjan's algorithm
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in graph[node]:
            if nxt not in index:
                connect(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            connect(node)
    loops = []
    for group in sorted(groups):
        start, members = group[0], set(group)
        paths = {start: [start]}
        frontier = [start]
        loop = None
        while frontier and loop is None:  # breadth first: the shortest way back to `start`
            nxt_frontier = []
            for node in frontier:
                for nxt in graph[node]:
                    if nxt == start:
                        loop = paths[node] + [start]
                        break
                    if nxt in members and nxt not in paths:
                        paths[nxt] = paths[node] + [nxt]
                        nxt_frontier.append(nxt)
                if loop:
                    break
            frontier = nxt_frontier
        loops.append((group, loop))
    return loops


def describe(group: list[str], loop: list[str], edges: dict[Edge, int]) -> str:
    steps = " -> ".join(f"{a} (line {edges[a, b]})" for a, b in zip(loop, loop[1:], strict=False))
    return f"{steps} -> {loop[-1]}" + (f"; all modules in this loop: {', '.join(group)}" if len(group) > 2 else "")


@pytest.fixture(scope="module")
def graph() -> tuple[dict[Edge, int], dict[str, dict[str, int]]]:
    return import_graph(PACKAGE_DIR)


def test_no_module_imports_itself_through_others(graph) -> None:
    edges, _ = graph
    problems = [describe(group, loop, edges) for group, loop in cycles(edges)]
    assert not problems, "import cycles:\n" + "\n".join(problems)


def test_the_model_imports_only_itself_the_config_and_the_data_format(graph) -> None:
    edges, _ = graph
    bad = [f"{a} imports {b} (line {line})" for (a, b), line in sorted(edges.items())
           if (a == MODEL or a.startswith(MODEL + ".")) and not (b == MODEL or b.startswith(MODEL + "."))
           and b not in MODEL_MAY_IMPORT]
    assert not bad, "the model reaches outside gns_bench.model:\n" + "\n".join(bad)


def test_only_tracking_imports_mlflow(graph) -> None:
    _, external = graph
    bad = [f"{name} imports mlflow (line {imported['mlflow']})" for name, imported in sorted(external.items())
           if "mlflow" in imported and name != MLFLOW_MODULE]
    assert not bad, f"MLflow outside {MLFLOW_MODULE}:\n" + "\n".join(bad)


def test_the_graph_resolves_relative_lazy_and_from_imports(tmp_path: Path) -> None:
    """The reader itself, on a small package: `from p.a import b` is module p.a.b when there is one, else
    p.a; relative imports resolve against the package; imports inside functions count."""
    files = {
        "pkg/__init__.py": "from pkg.a import helper\n",
        "pkg/a/__init__.py": "def helper():\n    from ..c import thing\n    return thing\n",
        "pkg/a/b.py": "import os\nfrom . import sibling\nfrom .sibling import name\n",
        "pkg/a/sibling.py": "from pkg.a import b\nimport mlflow.tracking\n",
        "pkg/c.py": "import pkg.a.b\nfrom pkg import a\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    edges, external = import_graph(tmp_path / "pkg")
    assert set(edges) == {("pkg", "pkg.a"), ("pkg.a", "pkg.c"), ("pkg.a.b", "pkg.a.sibling"),
                          ("pkg.a.sibling", "pkg.a.b"), ("pkg.c", "pkg.a.b"), ("pkg.c", "pkg.a")}
    assert edges["pkg.a", "pkg.c"] == 2  # the import inside `helper`
    assert external["pkg.a.sibling"] == {"mlflow": 2} and external["pkg.a.b"] == {"os": 1}
    assert cycles(edges) == [(["pkg.a", "pkg.c"], ["pkg.a", "pkg.c", "pkg.a"]),
                             (["pkg.a.b", "pkg.a.sibling"], ["pkg.a.b", "pkg.a.sibling", "pkg.a.b"])]
