"""The project's import graph: no circle, no arrow against the layer order envs < trackers <
training. Every import counts, also those inside functions (they hide circles from Python, not
from a reader), except those under ``if TYPE_CHECKING:`` (annotations only, never run)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("envs", "trackers", "training")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def project_modules() -> dict[str, Path]:
    return {
        module_name(path): path for layer in LAYERS for path in sorted((ROOT / layer).rglob("*.py"))
    }


def imported_modules(path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules ``path`` imports anywhere in its body: ``import a.b`` names ``a.b``;
    ``from a import b`` names ``a.b`` where that is a module, else ``a``."""
    found: set[str] = set()
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in list(ast.walk(tree)):
        if _type_checking_only(node):  # annotations only: never executed
            node.body = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [
                f"{node.module}.{alias.name}"
                if f"{node.module}.{alias.name}" in modules
                else node.module
                for alias in node.names
            ]
        else:
            continue
        found.update(name for name in names if name in modules)
    return found


def _type_checking_only(node: ast.AST) -> bool:
    return (
        isinstance(node, ast.If)
        and isinstance(node.test, ast.Name)
        and node.test.id == "TYPE_CHECKING"
    )


def import_graph() -> dict[str, set[str]]:
    modules = project_modules()
    return {name: imported_modules(path, modules) - {name} for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of modules (first repeated last), or None."""
    state: dict[str, int] = {}  # 1 on the current path, 2 done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def package_cycle_free(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The graph without the edges from a package's ``__init__`` to its own submodules: an
    ``__init__`` that re-exports its submodules is the package's front door, not a circle."""
    return {
        name: {dep for dep in deps if not dep.startswith(name + ".")}
        for name, deps in graph.items()
    }


def test_finds_a_planted_cycle_and_the_layer_rule() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_circle() -> None:
    cycle = find_cycle(package_cycle_free(import_graph()))
    assert cycle is None, "import circle: " + " -> ".join(cycle or [])


def test_imports_follow_the_layer_order() -> None:
    rank = {layer: i for i, layer in enumerate(LAYERS)}
    against = sorted(
        f"{name} imports {dep}"
        for name, deps in import_graph().items()
        for dep in deps
        if rank[dep.split(".")[0]] > rank[name.split(".")[0]]
    )
    assert not against, "imports against envs < trackers < training:\n" + "\n".join(against)
