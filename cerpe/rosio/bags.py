"""ROS bags through ``rosbags``: read ROS 1 ``.bag`` and ROS 2 bags (a folder with ``metadata.yaml``, a
bare ``.db3`` or ``.mcap``), write ROS 2 bags (``.mcap`` or sqlite3 folders) and ROS 1 ``.bag`` files.

Messages come out as ROS 2 objects of :func:`cerpe.rosio.types.typestore` whatever the bag's
version (:func:`to_ros2` maps a ROS 1 message field by field: ``Header.seq`` dropped, ``CameraInfo``'s
``D K R P`` lower-cased), so one decoder serves both. A bag that does not open is one
:class:`BagError` naming the file; a bag cut short raises :class:`BagTruncated` at the first
message that cannot be read, carrying how many were read before it.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

from ..errors import CerpeError
from .types import msg_class, typestore

BAG_SUFFIXES = (".bag", ".db3", ".mcap")
#: what to do with a bag that does not open, by suffix (a recording that was cut short has no index or footer)
REPAIR = {".bag": "if its recording was cut short, `rosbag reindex` it (ROS 1)",
          ".mcap": "if its recording was cut short, `mcap recover` it",
          ".db3": "if its recording was cut short, `ros2 bag reindex` its folder"}


class BagError(CerpeError, ValueError):
    """A bag that cannot be opened or read (names the file)."""


class BagTruncated(BagError):
    """A bag whose messages end in an unreadable part (cut short); ``n_read`` came before it."""

    def __init__(self, message: str, n_read: int) -> None:
        super().__init__(message)
        self.n_read = n_read


def _reader_errors() -> tuple[type[BaseException], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as R1
    from rosbags.rosbag2 import ReaderError as R2
    from rosbags.serde import SerdeError

    return AnyReaderError, R1, R2, SerdeError, OSError, EOFError, ValueError, KeyError, IndexError, AssertionError


def check_path(path: Path | str, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise BagError(f"{what}: bag not found: {p}")
    if p.is_file() and p.suffix not in BAG_SUFFIXES:
        raise BagError(f"{what}: {p} is not a bag ({', '.join(BAG_SUFFIXES)}, or a ROS 2 bag folder)")
    if p.is_dir() and not (p / "metadata.yaml").is_file():
        raise BagError(f"{what}: {p} is a folder without metadata.yaml: not a ROS 2 bag")
    return p


def _to(obj: Any, cls_of: Any) -> Any:
    """``obj`` (a rosbags message of one store) as the class of the same type in another store."""
    if isinstance(obj, list):
        return [_to(o, cls_of) for o in obj]
    kind = getattr(obj, "__msgtype__", None)
    if kind is None:
        return obj
    cls = cls_of(kind)
    values = {}
    for f in dataclasses.fields(cls):
        if f.name == "__msgtype__":
            continue
        for name in (f.name, f.name.upper(), f.name.lower()):
            if hasattr(obj, name):
                values[f.name] = _to(getattr(obj, name), cls_of)
                break
        else:
            values[f.name] = 0 if f.name == "seq" else None
    return cls(**values)


def to_ros2(msg: Any) -> Any:
    """A message read from any bag as the ROS 2 class of its type (a ROS 2 message comes back equal)."""
    return _to(msg, msg_class)


def to_ros1(msg: Any) -> Any:
    """A ROS 2 message as the ROS 1 (Noetic) class of its type (for writing ``.bag`` files)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    return _to(msg, lambda kind: store.types[kind])


class BagReader:
    """An open bag: its topics and their types, its messages in time order (a context manager)."""

    def __init__(self, path: Path | str, what: str = "bag") -> None:
        from rosbags.highlevel import AnyReader

        self.path, self.what = check_path(path, what), what
        try:
            self._reader = AnyReader([self.path], default_typestore=typestore())
            self._reader.open()
        except _reader_errors() as exc:
            raise BagError(f"{what}: {self.path} does not open as a ROS bag ({type(exc).__name__}: {exc}); "
                           f"{REPAIR.get(self.path.suffix, REPAIR['.db3'])}") from None
        self.ros1 = not self._reader.is2

    @property
    def topics(self) -> dict[str, str]:
        """topic -> message type (``pkg/msg/Name``)."""
        return {c.topic: c.msgtype for c in self._reader.connections}

    @property
    def duration_s(self) -> float:
        return self._reader.duration * 1e-9

    @property
    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for c in self._reader.connections:
            out[c.topic] = out.get(c.topic, 0) + int(getattr(c, "msgcount", 0) or 0)
        return out

    def messages(self, topics: Iterable[str], cdr: bool = False) -> Iterator[tuple[str, str, int, Any]]:
        """``(topic, msgtype, bag time ns, ROS 2 message)`` of ``topics`` in bag-time order; with ``cdr`` the
        message as ROS 2 CDR bytes (a ROS 2 bag's as stored, a ROS 1 bag's converted).

        Raises :class:`BagTruncated` at the first message that cannot be read or decoded.
        """
        wanted = set(topics)
        conns = [c for c in self._reader.connections if c.topic in wanted]
        n = 0
        it = self._reader.messages(connections=conns) if conns else iter(())
        while True:
            try:
                conn, t_ns, raw = next(it)
                if cdr and not self.ros1:
                    msg = bytes(raw)
                else:
                    msg = self._reader.deserialize(raw, conn.msgtype)
                    msg = to_ros2(msg) if self.ros1 else msg
                    if cdr:
                        msg = bytes(typestore().serialize_cdr(msg, conn.msgtype))
            except StopIteration:
                return
            except _reader_errors() as exc:
                raise BagTruncated(f"{self.what}: {self.path}: message {n + 1} of {sorted(wanted)} cannot be read "
                                   f"({type(exc).__name__}: {exc}); the bag may be cut short", n) from None
            n += 1
            yield conn.topic, conn.msgtype, int(t_ns), msg

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> "BagReader":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def write_bag(path: Path | str, messages: Iterable[tuple[str, str, int, Any]], storage: str = "mcap") -> Path:
    """Write ``(topic, msgtype, bag time ns, ROS 2 message)`` in that order to a bag.

    ``storage``: ``mcap`` (a ROS 2 folder holding one ``.mcap``), ``sqlite3`` (a ROS 2 folder
    holding one ``.db3``) or ``ros1`` (a ``.bag`` file; ``path`` should end in ``.bag``).
    Returns the bag's path (the folder for ROS 2).
    """
    path = Path(path)
    if path.exists():
        raise BagError(f"bag {path} exists already; remove it or choose another path")
    if storage == "ros1":
        return _write_ros1(path, messages)
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
    if storage not in plugins:
        raise BagError(f"bag storage {storage!r}: expected mcap, sqlite3 or ros1")
    conns: dict[str, Any] = {}
    with Writer(path, version=9, storage_plugin=plugins[storage]) as w:
        for topic, kind, t_ns, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, kind, typestore=typestore())
            w.write(conns[topic], int(t_ns), typestore().serialize_cdr(msg, kind))
    return path


def _write_ros1(path: Path, messages: Iterable[tuple[str, str, int, Any]]) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    conns: dict[str, Any] = {}
    with Writer(path) as w:
        for topic, kind, t_ns, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, kind, typestore=store)
            w.write(conns[topic], int(t_ns), store.serialize_ros1(to_ros1(msg), kind))
    return path


def topic_types(paths: Sequence[Path | str]) -> dict[str, dict[str, str]]:
    """bag path -> its topics and types (for error messages that list what a bag holds)."""
    out = {}
    for p in paths:
        with BagReader(p) as r:
            out[str(p)] = r.topics
    return out
