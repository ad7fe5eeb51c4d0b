"""Atomic file writes, checked output folders and checked JSON reads.

A file is written to a temporary name in its own folder (``.<name>.<pid>.tmp``)
and renamed over the target, so a reader never sees half a file and an
interrupted writer leaves only a ``.*.tmp`` leftover. Every failure is an
:class:`AtomicIOError` naming the file and what is wrong with it (a folder where
a file belongs, a file where a folder belongs, no permission), never a traceback.
Nothing here knows about runs, datasets or models.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import CerpeError

__all__ = ["AtomicIOError", "atomic_write_bytes", "atomic_write_text", "atomic_write_json", "atomic_write_npz",
           "check_file_target", "ensure_dir", "json_default", "read_json"]


class AtomicIOError(CerpeError, ValueError):
    """A file or folder that cannot be written or read as asked (the message names it)."""


def _file_in_the_way(p: Path) -> Path | None:
    """The existing non-folder among ``p`` and its parents (up to the first existing folder), or None."""
    for q in (p, *p.parents):
        if q.exists() or q.is_symlink():
            return None if q.is_dir() else q
    return None


def ensure_dir(path: Path | str, what: str = "output folder", create: bool = True) -> Path:
    """Create folder ``path`` (and its parents) unless it exists; return it.

    Raises :class:`AtomicIOError` naming ``what`` when ``path`` or one of its
    parents is an existing file, or the folder cannot be created. ``create=False``
    only checks that it could be a folder.
    """
    p = Path(path)
    q = _file_in_the_way(p)
    if q is not None:
        raise AtomicIOError(f"{what} {p}: " + ("exists and is not a folder" if q == p else f"{q} is a file, not a folder"))
    if create:
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise AtomicIOError(f"{what} {p}: cannot create it: {exc.strerror or exc}") from None
    return p


def check_file_target(path: Path | str, what: str = "cannot write") -> Path:
    """Raise :class:`AtomicIOError` unless ``path`` could be written as a file (no folder there, no file above)."""
    p = Path(path)
    if p.is_dir():
        raise AtomicIOError(f"{what} {p}: it is a folder")
    q = _file_in_the_way(p.parent)
    if q is not None:
        raise AtomicIOError(f"{what} {p}: {q} is a file, not a folder")
    return p


def atomic_write_bytes(path: Path | str, data: bytes, durable: bool = True) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder + rename.

    ``durable`` flushes the file to disk before the rename (``fsync``); a writer of
    many small files that renames a whole folder at the end may skip it.
    """
    path = check_file_target(path)
    ensure_dir(path.parent, f"cannot write {path.name} into")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            if durable:
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise AtomicIOError(f"cannot write {path}: {exc.strerror or exc}") from None


def atomic_write_text(path: Path | str, text: str, durable: bool = True) -> None:
    atomic_write_bytes(path, text.encode("utf-8"), durable)


def atomic_write_npz(path: Path | str, **arrays: Any) -> None:
    """``np.savez(path, **arrays)``, atomically (the archive built in memory, then
    :func:`atomic_write_bytes`): a reader never sees half an archive, a failure is an
    :class:`AtomicIOError` naming the file. ``path`` is written as given (no ``.npz`` added)."""
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def json_default(o: Any) -> Any:
    """JSON form of numpy scalars and arrays, paths and dataclasses (``repr`` for anything else)."""
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if is_dataclass(o):
        return asdict(o)
    return repr(o)


def atomic_write_json(path: Path | str, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=json_default) + "\n")


def read_json(path: Path | str, what: str) -> dict:
    """Read a JSON object; a missing, unreadable, truncated or non-object file raises naming it."""
    path = Path(path)
    try:
        obj = json.loads(path.read_text())
    except FileNotFoundError:
        raise AtomicIOError(f"{what}: file not found: {path}") from None
    except NotADirectoryError:
        raise AtomicIOError(f"{what}: {path.parent} is a file, not a folder") from None
    except IsADirectoryError:
        raise AtomicIOError(f"{what}: {path} is a folder, not a file") from None
    except OSError as exc:
        raise AtomicIOError(f"{what}: cannot read {path}: {exc.strerror or exc}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise AtomicIOError(f"{what}: corrupt or half-written JSON in {path}: {exc}") from None
    if not isinstance(obj, dict):
        raise AtomicIOError(f"{what}: expected a JSON object in {path}")
    return obj
