"""Frames arriving from the team, on Zenoh's threads: checked, decoded and filed in the mailbox;
and the counting of what is wrong with them (each degradation once per cause where it repeats).

A mixin of :class:`~cerpe.online.zenoh_link.ZenohLink` (it reads the link's roster, mailbox and
peer sets, always under the link's lock); apart so that the link module stays the engine's link
protocol. What is counted and why: :mod:`cerpe.online.zenoh_link`.
"""
from __future__ import annotations

import logging
import threading
from collections import Counter
from typing import TYPE_CHECKING, Any

from ..messages import Message, MessageError, decode
from . import zenoh_wire as w

if TYPE_CHECKING:  # the attributes the mixin reads, owned by ZenohLink
    from ..algorithm.link import Mailbox

log = logging.getLogger(__name__)


class ReceiveSide:
    """Filing the team's frames and counting degradations, for :class:`~cerpe.online.zenoh_link.ZenohLink`."""

    if TYPE_CHECKING:
        robot_id: str
        robot_ids: list[str]
        index_of: dict[str, int]
        team: str
        box: Mailbox
        stats: Counter[str]
        _cond: threading.Condition
        _last: dict[str, dict[str, int]]
        _gone: set[str]
        _said_bye: set[str]
        _leaving: dict[str, float]
        _reported: set[tuple]
        _events: list[tuple[str, str]]
        wire: w.Wire

        def _stream_file(self, robot: str, kind: str, msg: Message, nbytes: int, stamp_s: float,
                         clock_s: float) -> None: ...

    # ------------------------------------------------------------------ counting
    def _degrade(self, what: str) -> None:
        """Queue one degradation for the next inbox (caller holds the lock)."""
        self.box.degrade(what)

    def _once(self, what: str, robot: str, detail: str, message: str) -> None:
        """Count ``what`` and log ``message`` the first time for ``(robot, detail)`` (lock held)."""
        if (what, robot, detail) in self._reported:
            return
        self._reported.add((what, robot, detail))
        self._degrade(what)
        log.warning("robot %s: %s", self.robot_id, message)

    def take_degradations(self) -> list[str]:
        """Degradations counted since the last gather (and not handed out by it)."""
        with self._cond:
            return self.box.inbox(self.box.step, "", []).degradations

    # ------------------------------------------------------------------ receiving (Zenoh threads)
    def _on_sample(self, sample: Any) -> None:
        key = w.parse_data_key(str(sample.key_expr))
        payload, attachment = w.as_bytes(sample.payload) or b"", w.as_bytes(sample.attachment)
        with self._cond:
            self.stats["frames_received"] += 1
            self._file(key, payload, attachment)
            self._cond.notify_all()

    def _protocol_mismatch(self, robot: str, tag: str) -> None:
        """Count and name a robot of another link protocol version, once (lock held)."""
        self._once("link:protocol-mismatch", robot, tag,
                   f"robot {robot} speaks cerpe link protocol {w.describe_tag(tag)}, this robot "
                   f"{w.describe_tag(self.wire.tag)}: its frames and requests are ignored (run the same cerpe "
                   f"version, and --lockstep on all robots or on none)")

    def _decode(self, robot: str, payload: bytes, attachment: bytes | None) -> Message | None:
        """The message of a payload that carries our header; None, counted, for anything else (lock held)."""
        status = self.wire.parse(attachment)[0]
        if status == "protocol":
            self._protocol_mismatch(robot, w.header_tag(attachment))
            self.stats["frames_foreign_protocol"] += 1
            return None
        try:
            if status == "ok":
                return decode(payload)
        except MessageError as exc:
            log.debug("robot %s: garbled frame from %s: %s", self.robot_id, robot, exc)
        self._degrade("msg:garbled")
        return None

    def _file(self, key: tuple[str, str, str] | None, payload: bytes, attachment: bytes | None) -> None:
        if key is None:
            self._degrade("msg:garbled")
            return
        _, robot, kind = key
        if robot == self.robot_id:
            self._once("link:duplicate-robot", robot, "", f"another Zenoh session publishes as robot {robot} "
                       f"in team {self.team}: two robots were started with the same id")
            return
        if robot not in self.index_of:
            self._degrade("msg:unknown-sender")
            log.debug("robot %s: frame from robot %r, not in the roster %s", self.robot_id, robot, self.robot_ids)
            return
        if kind == w.BYE:
            if self.wire.parse(attachment)[0] == "ok":
                if robot not in self._gone:
                    self._events.append((robot, "gone"))
                self._said_bye.add(robot)
                self._gone.add(robot)
                self._leaving.pop(robot, None)  # its token went first: not lost after all
            return
        msg = self._decode(robot, payload, attachment)
        if msg is None:
            return
        if w.KIND_OF_TYPE.get(msg.TYPE) != kind:
            self._degrade("msg:garbled")
            log.debug("robot %s: a %s frame on %s's %s key", self.robot_id, type(msg).__name__, robot, kind)
            return
        if msg.sender != self.index_of[robot]:
            self._degrade("msg:unknown-sender")
            log.debug("robot %s: frame on %s's key says sender index %d", self.robot_id, robot, msg.sender)
            return
        if self.wire.mode == "stamps":
            _, stamp, clock = self.wire.parse(attachment)
            self._stream_file(robot, kind, msg, len(payload), stamp, clock)
            return
        last = self._last[robot]
        last[kind] = max(last.get(kind, -1), int(msg.step))
        self.box.file(robot, msg, len(payload))  # late, too far ahead, duplicate: counted in stats
