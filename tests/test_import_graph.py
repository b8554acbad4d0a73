"""No import circle anywhere in the project: the module graph of engine/, drivers/, server/, frontend/ and
bench/, every import statement counted (function-level and ``TYPE_CHECKING`` ones too), has no cycle, and
its arrows point inward as ``docs/ARCHITECTURE.md`` draws them.

A circle forces imports into functions to dodge it, hides which room depends on which, and breaks when
someone moves an import to the top. When this fails, move what both modules need into a module of its own
(as ``engine.tones`` and ``engine.solvers.base`` were made), rather than importing inside a function.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("engine", "drivers", "server", "frontend", "bench")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imported(node: ast.Import | ast.ImportFrom, module: str, is_package: bool, known: set[str]) -> list[str]:
    """The project modules one import statement loads (``from a import b`` loads ``a.b`` when that is a module)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        if node.level:
            base = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
            stem = ".".join([*base, node.module] if node.module else base)
        else:
            stem = node.module or ""
        names = [f"{stem}.{alias.name}" if f"{stem}.{alias.name}" in known else stem for alias in node.names]
    out = []
    for name in names:
        while name and name not in known:  # ``import engine.solvers.redrec`` of a module; ``import numpy``: none
            name = name.rpartition(".")[0]
        if name:
            out.append(name)
    return out


def import_graph() -> dict[str, set[str]]:
    """module -> the project modules it imports anywhere in its text."""
    files = {(_module_name(p), p) for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")}
    known = {name for name, _ in files}
    graph: dict[str, set[str]] = {}
    for name, path in files:
        tree = ast.parse(path.read_text(), filename=str(path))
        edges = graph.setdefault(name, set())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import | ast.ImportFrom):
                edges.update(_imported(node, name, path.name == "__init__.py", known))
        edges.discard(name)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_graph_sees_every_kind_of_import() -> None:
    graph = import_graph()
    assert {"engine.config", "engine.solvers", "bench.solvers", "server.cli", "drivers.sim.world"} <= set(graph)
    assert "engine.config" in graph["engine.engine"]  # a top-level ``from engine.config import ...``
    assert "engine.solvers.validate" in graph["bench.solvers"]  # ``from engine.solvers.validate import ...``
    assert "drivers.sim.lab" in graph["server.cli"]  # function-level imports count too
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_circle() -> None:
    found = cycles(import_graph())
    assert not found, "import circles (move what both sides need into a module of its own):\n" + "\n".join(
        " <-> ".join(c) for c in found
    )


def test_rooms_import_inward() -> None:
    """engine imports no other room; drivers and frontend only engine; only the command line reaches bench."""
    allowed = {
        "engine": {"engine"},
        "drivers": {"engine", "drivers"},
        "frontend": {"engine", "frontend"},
        "server": {"engine", "drivers", "frontend", "server"},
        "bench": {"engine", "drivers", "server", "bench"},
    }
    wrong = [
        f"{module} imports {target}"
        for module, targets in sorted(import_graph().items())
        for target in sorted(targets)
        if target.split(".")[0] not in allowed[module.split(".")[0]] and module != "server.cli"
    ]
    assert not wrong, "imports against the direction in docs/ARCHITECTURE.md:\n" + "\n".join(wrong)
