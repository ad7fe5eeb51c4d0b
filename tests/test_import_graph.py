"""cerpe's imports go one way: no circle between packages, none between modules.

Walks every module with ``ast``. An edge A -> B means module A names module B in one of:

- a module-level import (runs when A is imported; ``if`` / ``try`` blocks included);
- a deferred import (inside a function or method): deferring hides a circle from Python,
  not from the design;
- a string: in a module that loads modules by name (calls ``importlib.import_module``), a
  string literal naming a cerpe module, ``"cerpe.x.y"`` or ``"cerpe.x.y:Attr"`` as entry
  points spell it (the CLI's sub-command table, the dataset adapters' registry).

An edge names the most specific module: ``from . import writer`` is an edge to
``cerpe.synth.writer``, ``from .registry import get_adapter`` one to ``cerpe.datasets.registry``;
the parent package a submodule import loads first is not an edge. Two granularities: a
"package" is ``cerpe.X`` for a sub-package and each top-level module on its own
(``cerpe.geometry``, ``cerpe.depthsim``...), where module-level imports alone must not circle
and neither must all of them; and modules, where no circle may pass through any kind of edge.
"""
from __future__ import annotations

import ast
from pathlib import Path
from typing import Iterator

import cerpe

PKG = Path(cerpe.__file__).resolve().parent


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES: dict[str, Path] = {module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def _resolve(mod: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _known(name: str) -> str:
    """``name`` cut back to a module that exists (``cerpe.x.y.attr`` -> ``cerpe.x.y``)."""
    while name not in MODULES and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def _module_level(body: list[ast.stmt]) -> Iterator[ast.stmt]:
    """The statements that run on import: the body, and the bodies of its ``if`` / ``try`` blocks."""
    for node in body:
        yield node
        if isinstance(node, (ast.If, ast.Try)):
            yield from _module_level(node.body)
            yield from _module_level(node.orelse)
            for handler in getattr(node, "handlers", []):
                yield from _module_level(handler.body)
            yield from _module_level(getattr(node, "finalbody", []))


def _loads_by_name(tree: ast.Module) -> bool:
    return any(isinstance(n, ast.Call) and (getattr(n.func, "attr", None) == "import_module"
                                            or getattr(n.func, "id", None) == "import_module")
               for n in ast.walk(tree))


def imported_modules(path: Path, *, deferred: bool) -> set[str]:
    """The cerpe modules ``path`` imports at module level, or (``deferred``) in any of the three ways."""
    mod, is_pkg = module_name(path), path.name == "__init__.py"
    tree = ast.parse(path.read_text(), str(path))
    out: set[str] = set()
    for node in ast.walk(tree) if deferred else _module_level(tree.body):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(mod, is_pkg, node)
            for alias in node.names:  # `from . import writer` names a module, `from .x import f` an attribute
                out.add(f"{target}.{alias.name}" if f"{target}.{alias.name}" in MODULES else target)
    if deferred and _loads_by_name(tree):
        out.update(n.value.split(":")[0] for n in ast.walk(tree)
                   if isinstance(n, ast.Constant) and isinstance(n.value, str)
                   and n.value.split(":")[0] in MODULES)
    return {_known(m) for m in out if m.startswith("cerpe.")} - {mod}


def package_of(module: str) -> str:
    return ".".join(module.split(".")[:2])


def module_graph(*, deferred: bool = True) -> dict[str, set[str]]:
    return {mod: imported_modules(path, deferred=deferred) for mod, path in MODULES.items()}


def package_graph(*, deferred: bool = False) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for mod, targets in module_graph(deferred=deferred).items():
        for target in targets:
            if package_of(target) not in (package_of(mod), "cerpe"):
                graph.setdefault(package_of(mod), set()).add(package_of(target))
    return graph


def circle_groups(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of two or more nodes that all reach each other (strongly connected components),
    each sorted, in sorted order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def connect(n: str) -> None:  # Tarjan's algorithm
        index[n] = low[n] = len(index)
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if m not in index:
                connect(m)
                low[n] = min(low[n], low[m])
            elif m in stack:
                low[n] = min(low[n], index[m])
        if low[n] == index[n]:
            group = []
            while not group or group[-1] != n:
                group.append(stack.pop())
            if len(group) > 1:
                groups.append(sorted(group))

    for n in sorted(graph):
        if n not in index:
            connect(n)

    return sorted(groups)


def shortest_circle(graph: dict[str, set[str]], group: list[str]) -> list[str]:
    """The shortest circle from ``group[0]`` back to itself, breadth first within the group."""
    start, members = group[0], set(group)
    came_from: dict[str, str] = {}
    frontier = [start]
    while start not in came_from:
        reached = []
        for n in frontier:
            for m in sorted(graph.get(n, set()) & members):
                if m not in came_from:
                    came_from[m] = n
                    reached.append(m)
        frontier = reached
    path = [start]
    while len(path) == 1 or path[-1] != start:
        path.append(came_from[path[-1]])
    return path[::-1]


def _describe(graph: dict[str, set[str]], groups: list[list[str]]) -> str:
    """One line per group: its shortest circle, then every module in it."""
    return "\n".join(f"{' -> '.join(shortest_circle(graph, g))}   (all {len(g)}: {', '.join(g)})" for g in groups)


def test_the_walk_sees_a_circle_when_there_is_one() -> None:
    assert circle_groups({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c"]]
    assert circle_groups({"a": {"b"}, "b": {"c"}}) == []
    assert circle_groups({"a": {"b", "d"}, "b": {"a"}, "c": {"d"}, "d": {"c"}}) == [["a", "b"], ["c", "d"]]
    loop = {"a": {"b", "c"}, "b": {"c"}, "c": {"a"}}
    assert shortest_circle(loop, ["a", "b", "c"]) == ["a", "c", "a"]  # not a -> b -> c -> a


def test_the_walk_reads_relative_imports() -> None:
    imports = imported_modules(PKG / "backbones" / "depth.py", deferred=False)
    assert "cerpe.depthsim" in imports and "cerpe.protocols" in imports
    graph = package_graph()
    assert "cerpe.depthsim" in graph["cerpe.backbones"]
    assert "cerpe.synth" not in graph.get("cerpe.backbones", set())  # the depth simulators moved out


def test_the_walk_reads_deferred_imports_and_module_names() -> None:
    lazy = imported_modules(PKG / "synth" / "__init__.py", deferred=True)
    assert "cerpe.synth.writer" in lazy and "cerpe.synth.worlds" in lazy  # `from . import writer` in a function
    assert "cerpe.synth.writer" not in imported_modules(PKG / "synth" / "__init__.py", deferred=False)
    assert "cerpe.synth" not in lazy  # names the module, not its package
    cli = imported_modules(PKG / "cli.py", deferred=True)
    assert {"cerpe.pipeline.run", "cerpe.synth.cli"} <= cli  # _register("run", "cerpe.pipeline.run", ...)
    assert "cerpe.datasets.synthetic" in imported_modules(PKG / "datasets" / "registry.py", deferred=True)
    assert "cerpe.synth" in package_graph(deferred=True)["cerpe.datasets"]  # synthetic generates on demand


def test_no_circle_between_packages() -> None:
    graph = package_graph()
    assert graph, "the walk found no imports at all"
    groups = circle_groups(graph)
    assert not groups, "import circle between packages:\n" + _describe(graph, groups)


def test_no_circle_between_packages_even_through_deferred_imports() -> None:
    graph = package_graph(deferred=True)
    groups = circle_groups(graph)
    assert not groups, "import circle between packages (deferred imports included):\n" + _describe(graph, groups)


def test_no_circle_between_modules() -> None:
    """Within a package too: a concept has one owner that the others import, never the reverse."""
    graph = module_graph()
    groups = circle_groups(graph)
    assert not groups, "import circle between modules (deferred imports, names included):\n" + _describe(graph, groups)
