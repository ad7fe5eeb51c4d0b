"""Which cerpe modules a cerpe module imports, read from its source with ``ast`` (nothing is imported).

One parser for two users: the import-graph tests (no circle between packages or modules) and
the code fingerprint of a method's runs (:func:`cerpe.runfolder.provenance.code_hash`: the
modules its code reaches).

An edge A -> B means module A names module B in one of three ways:

- a module-level import (runs when A is imported; ``if`` / ``try`` blocks included);
- a deferred import (inside a function or method);
- a string: in a module that loads modules by name (calls ``importlib.import_module``), a
  string literal naming a cerpe module, ``"cerpe.x.y"`` or ``"cerpe.x.y:Attr"`` as entry
  points spell it (the CLI's sub-command table, the dataset adapters' registry).

An edge names the most specific module: ``from . import writer`` is an edge to
``cerpe.synth.writer``, ``from .registry import get_adapter`` one to ``cerpe.datasets.registry``;
the parent package a submodule import loads first is not an edge (:func:`closure` adds it).
Every function takes the package folder, so a copy of the package can be read as well.
"""
from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Iterator

PKG = Path(__file__).resolve().parent  # the cerpe package folder


def module_name(path: Path, pkg: Path = PKG) -> str:
    """``cerpe.x.y`` of the file ``path`` of the package folder ``pkg`` (``cerpe.x`` for ``x/__init__.py``)."""
    parts = Path(path).relative_to(Path(pkg).parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules(pkg: Path = PKG) -> dict[str, Path]:
    """Every module of the package folder ``pkg``: ``{name: file}``, sorted by file."""
    return {module_name(p, pkg): p for p in sorted(Path(pkg).rglob("*.py")) if "__pycache__" not in p.parts}


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


Statement = tuple  # ("import", name) | ("from", level, module, names)


def _parsed(path: Path) -> tuple[tuple[Statement, ...], tuple[Statement, ...], tuple[str, ...], bool]:
    """``(module-level imports, every import, string literals, loads by name)`` of the module file ``path``."""
    source = Path(path).read_bytes()
    try:
        return _parsed_source(source)
    except SyntaxError as exc:
        raise SyntaxError(f"{path}: {exc}") from None


@lru_cache(maxsize=None)
def _parsed_source(source: bytes) -> tuple[tuple[Statement, ...], tuple[Statement, ...], tuple[str, ...], bool]:
    """:func:`_parsed` of one source text, remembered by the text itself: an edited file is parsed again,
    an unchanged one (or a copy) is not (the parse is the slow part)."""
    tree = ast.parse(source)

    def statements(nodes: Iterable[ast.AST]) -> tuple[Statement, ...]:
        out: list[Statement] = []
        for node in nodes:
            if isinstance(node, ast.Import):
                out += [("import", a.name) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                out.append(("from", node.level, node.module, tuple(a.name for a in node.names)))
        return tuple(out)

    strings = tuple(n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str))
    return statements(_module_level(tree.body)), statements(ast.walk(tree)), strings, _loads_by_name(tree)


def _resolve(mod: str, is_pkg: bool, level: int, module: str | None) -> str:
    if level == 0:
        return module or ""
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def _known(name: str, known: dict[str, Path]) -> str:
    """``name`` cut back to a module that exists (``cerpe.x.y.attr`` -> ``cerpe.x.y``)."""
    while name not in known and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def imported_modules(path: Path, *, deferred: bool, pkg: Path = PKG, known: dict[str, Path] | None = None) -> set[str]:
    """The cerpe modules ``path`` imports at module level, or (``deferred``) in any of the three ways."""
    known = modules(pkg) if known is None else known
    path = Path(path)
    mod, is_pkg = module_name(path, pkg), path.name == "__init__.py"
    top, every, strings, by_name = _parsed(path)
    out: set[str] = set()
    for st in every if deferred else top:
        if st[0] == "import":
            out.add(st[1])
            continue
        target = _resolve(mod, is_pkg, st[1], st[2])
        for name in st[3]:  # `from . import writer` names a module, `from .x import f` an attribute
            out.add(f"{target}.{name}" if f"{target}.{name}" in known else target)
    if deferred and by_name:
        out.update(s.split(":")[0] for s in strings if s.split(":")[0] in known)
    root = Path(pkg).name + "."
    return {_known(m, known) for m in out if m.startswith(root)} - {mod}


def module_graph(*, deferred: bool = True, pkg: Path = PKG) -> dict[str, set[str]]:
    """``{module: the modules it imports}`` of every module of ``pkg``."""
    known = modules(pkg)
    return {mod: imported_modules(path, deferred=deferred, pkg=pkg, known=known) for mod, path in known.items()}


def closure(entries: Iterable[str], pkg: Path = PKG) -> list[str]:
    """Every module the code of ``entries`` can run: the entries, what they import in any of the three
    ways, transitively, and the packages (``__init__``) above each, which Python runs first. Sorted."""
    known = modules(pkg)
    todo = list(entries)
    unknown = [e for e in todo if e not in known]
    if unknown:
        raise ValueError(f"not modules of {pkg}: {unknown}")
    seen: set[str] = set()
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        seen.add(mod)
        parents = [".".join(mod.split(".")[:k]) for k in range(1, mod.count(".") + 1)]
        todo += [p for p in parents if p in known]
        todo += sorted(imported_modules(known[mod], deferred=True, pkg=pkg, known=known))
    return sorted(seen)


def data_files_named(mods: Iterable[str], data_dir: Path, pkg: Path = PKG) -> list[Path]:
    """The files of ``data_dir`` whose name one of ``mods`` spells as a string literal (the files it reads)."""
    known = modules(pkg)
    files = {p.name: p for p in sorted(Path(data_dir).glob("*")) if p.is_file()}
    named: set[str] = set()
    for mod in mods:
        strings = _parsed(known[mod])[2]
        named.update(s for s in strings if s in files)
    return [files[n] for n in sorted(named)]
