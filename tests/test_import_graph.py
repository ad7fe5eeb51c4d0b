"""cerpe's packages import each other in one direction: no circle between packages.

Walks every module with ``ast`` and keeps its module-level imports (those that run
when the module is imported; imports inside functions are deferred on purpose and
left out). A "package" is ``cerpe.X`` for a sub-package and each top-level module
on its own (``cerpe.geometry``, ``cerpe.depthsim``...); an edge A -> B means a module
of A imports a module of B at module level.
"""
from __future__ import annotations

import ast
from pathlib import Path

import cerpe

PKG = Path(cerpe.__file__).resolve().parent


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _resolve(mod: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def module_level_imports(path: Path) -> set[str]:
    """Fully qualified ``cerpe`` modules imported at module level (``if`` / ``try`` blocks included)."""
    mod, is_pkg = module_name(path), path.name == "__init__.py"
    out: set[str] = set()

    def visit(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                target = _resolve(mod, is_pkg, node)
                out.add(target)
                out.update(f"{target}.{a.name}" for a in node.names)  # `from . import writer`
            elif isinstance(node, (ast.If, ast.Try)):
                visit(node.body)
                visit(node.orelse)
                for h in getattr(node, "handlers", []):
                    visit(h.body)
                visit(getattr(node, "finalbody", []))

    visit(ast.parse(path.read_text(), str(path)).body)
    return {m for m in out if m == "cerpe" or m.startswith("cerpe.")}


def package_of(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "cerpe"
    return ".".join(parts[:2])


def package_graph() -> dict[str, set[str]]:
    known = {module_name(p) for p in PKG.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for path in sorted(PKG.rglob("*.py")):
        src = package_of(module_name(path))
        for target in module_level_imports(path):
            while target not in known and "." in target:  # `from .x import name` names an attribute
                target = target.rsplit(".", 1)[0]
            dst = package_of(target)
            if dst not in (src, "cerpe"):
                graph.setdefault(src, set()).add(dst)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (c := dfs(m)):
                return c
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (c := dfs(n)):
            return c
    return None


def test_no_circle_between_packages() -> None:
    graph = package_graph()
    assert graph, "the walk found no imports at all"
    cycle = find_cycle(graph)
    assert cycle is None, "import circle between packages: " + " -> ".join(cycle)


def test_the_walk_sees_a_circle_when_there_is_one() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}}) is None


def test_the_walk_reads_relative_imports() -> None:
    imports = module_level_imports(PKG / "backbones" / "depth.py")
    assert "cerpe.depthsim" in imports and "cerpe.protocols" in imports
    graph = package_graph()
    assert "cerpe.depthsim" in graph["cerpe.backbones"]
    assert "cerpe.synth" not in graph.get("cerpe.backbones", set())  # the depth simulators moved out


def all_imports(path: Path) -> set[str]:
    """Every ``cerpe`` module ``path`` imports, deferred (in-function) imports included."""
    mod, is_pkg = module_name(path), path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(mod, is_pkg, node)
            out.add(target)
            out.update(f"{target}.{a.name}" for a in node.names)
    return {m for m in out if m == "cerpe" or m.startswith("cerpe.")}


def test_no_circle_even_through_deferred_imports(monkeypatch) -> None:
    """Deferring an import inside a function hides a circle from Python, not from the design."""
    monkeypatch.setattr(__import__(__name__), "module_level_imports", all_imports)
    graph = package_graph()
    assert "cerpe.synth" in graph["cerpe.datasets"]  # the synthetic adapter generates on demand
    cycle = find_cycle(graph)
    assert cycle is None, "import circle between packages (deferred imports included): " + " -> ".join(cycle)
