"""The house's layers, read from the code's own imports (``ast``, nothing imported): no
import cycle between modules or between packages, and nothing below imports from above."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("protocol", "processes", "world_server", "channel_proxy", "vehicle_agent", "deploy", "bench")
# what each low package may never import: the run's participants and what they stand on
# know nothing of the launcher or the benches
NEVER = {low: ("deploy", "bench") for low in ("protocol", "processes", "world_server", "channel_proxy", "vehicle_agent")}


def modules() -> dict[str, Path]:
    """Every module of the project's packages by dotted name (a package by its own name)."""
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def imported(name: str, path: Path, known: dict[str, Path]) -> Iterator[str]:
    """The project modules ``name`` imports, wherever in the file (a function's import too)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*package.split(".")[: len(package.split(".")) - node.level + 1], *filter(None, [base])])
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in known:  # a name inside a module: the module
                target = target.rpartition(".")[0]
            if target and target != name:
                yield target


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: set(imported(name, path, known)) for name, path in known.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
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

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def package_of(module: str, known: dict[str, Path]) -> str:
    """The package (folder) a module lives in; a package's ``__init__`` is its own."""
    return module if known[module].name == "__init__.py" else module.rpartition(".")[0]


def test_no_module_imports_itself_through_others():
    assert cycles(graph()) == []


def test_no_package_imports_itself_through_others():
    known = modules()
    edges: dict[str, set[str]] = {}
    for module, targets in graph().items():
        mine = package_of(module, known)
        edges.setdefault(mine, set()).update({package_of(t, known) for t in targets} - {mine})
    assert cycles(edges) == []


def test_nothing_below_imports_the_launcher_or_the_benches():
    wrong = sorted(f"{module} -> {target}" for module, targets in graph().items() for target in targets
                   if target.split(".")[0] in NEVER.get(module.split(".")[0], ()))
    assert wrong == []


def test_the_reader_sees_an_import_cycle_and_an_upward_import():
    """The checks above can fail: a made-up loop and a made-up arrow up are found."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    edges = graph()
    assert "protocol.codec" in edges and "processes.manager" in edges["deploy.launch.run"]
