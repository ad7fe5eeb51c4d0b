"""cerpe's imports go one way: no circle between packages, none between modules.

The edges are :mod:`cerpe.importgraph`'s (module-level, deferred and by-name imports; the same
parser gives a method's code fingerprint): deferring an import hides a circle from Python, not
from the design. Two granularities: a
"package" is ``cerpe.X`` for a sub-package and each top-level module on its own
(``cerpe.geometry``, ``cerpe.depthsim``...), where module-level imports alone must not circle
and neither must all of them; and modules, where no circle may pass through any kind of edge.
"""
from __future__ import annotations

from cerpe.importgraph import PKG, imported_modules, module_graph


def package_of(module: str) -> str:
    return ".".join(module.split(".")[:2])


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
