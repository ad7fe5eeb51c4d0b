"""Answering the peers' image requests: queries checked on Zenoh's threads, answered on the robot's.

A bad query is refused at once and a good one queued. In lock-step, the robot's handler answers it
on the thread that calls the link, inside its waits, once the robot has begun the query's step; by
stamps, a serving thread of the link's answers it at once (:mod:`cerpe.online.zenoh_stream`).

A mixin of :class:`~cerpe.online.zenoh_link.ZenohLink` (it reads the link's roster, mailbox step and
counters, under the link's lock); apart so that the link module stays the engine's link protocol.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from typing import TYPE_CHECKING, Any, Callable, Mapping

from ..algorithm.link import RequestHandler
from ..errors import CerpeError
from ..messages import ImageRequest, Message
from . import zenoh_wire as w

if TYPE_CHECKING:  # the attributes the mixin reads, owned by ZenohLink
    from ..algorithm.link import Mailbox

log = logging.getLogger(__name__)


class ServeSide:
    """Image queries in, replies out, for :class:`~cerpe.online.zenoh_link.ZenohLink`."""

    if TYPE_CHECKING:
        conf: Mapping[str, Any]
        robot_id: str
        robot_ids: list[str]
        index: int
        team: str
        box: Mailbox
        stats: Counter[str]
        wire: w.Wire
        _cond: threading.Condition
        _queries: list[tuple[Any, str, ImageRequest, float]]
        _handler: RequestHandler | None

        def _degrade(self, what: str) -> None: ...
        def clock_now(self) -> float | None: ...
        def _protocol_mismatch(self, robot: str, tag: str) -> None: ...
        def _decode(self, robot: str, payload: bytes, attachment: bytes | None) -> Message | None: ...

    # ------------------------------------------------------------------ queries (Zenoh threads)
    def _on_query(self, query: Any) -> None:
        """Check an image query in the Zenoh thread: refuse a bad one at once, queue a good one."""
        payload, attachment = w.as_bytes(query.payload) or b"", w.as_bytes(query.attachment)
        with self._cond:
            reason, peer, req = self._check_query(payload, attachment)
            if reason is None and len(self._queries) >= int(self.conf["max_queued_queries"]):
                reason = "busy"
            if reason is None:
                self._queries.append((query, peer, req, self.wire.parse(attachment)[1]))
                self._cond.notify_all()
                return
            self.stats[f"queries_refused_{reason}"] += 1
        with query:
            query.reply_err(self.wire.error_payload(reason))

    def _check_query(self, payload: bytes, attachment: bytes | None) -> tuple[str | None, str, Any]:
        """``(refusal reason or None, peer, request)`` (lock held)."""
        if self.wire.parse(attachment)[0] == "protocol":
            self._protocol_mismatch("?", w.header_tag(attachment))
            return "protocol", "", None
        req = self._decode("?", payload, attachment)
        if req is None:
            return "garbled", "", None
        if not isinstance(req, ImageRequest) or req.target != self.index:
            self._degrade("msg:garbled")
            return ("garbled" if not isinstance(req, ImageRequest) else "wrong-target"), "", None
        if not (0 <= req.sender < len(self.robot_ids)) or req.sender == self.index:
            self._degrade("msg:unknown-sender")
            return "garbled", "", None
        return None, self.robot_ids[req.sender], req

    # ------------------------------------------------------------------ serving (caller's thread)
    def serve(self, handler: RequestHandler) -> None:
        """Answer image requests with ``handler(peer, request) -> reply frame | None``.

        Called on the thread that calls the link, inside its waits, for requests
        of a step this robot has begun (earlier ones too: the handler decides
        what is stale). None means "image not held": the requester counts
        ``msg:image-not-held``. A :class:`CerpeError` from the handler is logged
        and answered as an error; other exceptions propagate to the caller.
        """
        self._handler = handler

    def poll(self, timeout_s: float = 0.0) -> None:
        """Answer image queries for ``timeout_s`` (0: those waiting now); use it instead of sleeping."""
        self._wait(lambda: False, time.monotonic() + max(0.0, float(timeout_s)))

    def _serve_queries(self) -> None:
        if self._handler is None or self.wire.mode != "lockstep":  # by stamps: a thread of its own serves
            return
        with self._cond:
            ready = [q for q in self._queries if q[2].step <= self.box.step]
            self._queries = [q for q in self._queries if q[2].step > self.box.step]
        for query, peer, req, stamp in ready:
            with query:
                self._answer(query, peer, req, stamp)

    def _answer(self, query: Any, peer: str, req: ImageRequest, stamp_s: float) -> None:
        try:
            reply = self._handler(peer, req)
        except CerpeError as exc:
            log.warning("robot %s: image request of %s for step %d failed: %s", self.robot_id, peer, req.step, exc)
            reply, reason = None, "error"
        else:
            reason = w.NOT_HELD
        self._send_reply(query, reply, reason, stamp_s)

    def _send_reply(self, query: Any, reply: bytes | None, reason: str, stamp_s: float) -> None:
        """Reply ``reply`` (None: refuse with ``reason``), counted."""
        with self._cond:
            if reply is None:
                self.stats[f"queries_refused_{reason}"] += 1
            else:
                self.stats["replies_sent"] += 1
                self.stats["wire_bytes_reply"] += len(reply) + self.wire.size
        if reply is None:
            query.reply_err(self.wire.error_payload(reason))
        else:
            query.reply(w.image_key(self.team, self.robot_id), bytes(reply),
                        attachment=self.wire.attachment(stamp_s, self.clock_now()))

    # ------------------------------------------------------------------ waiting
    def _wait(self, done: Callable[[], bool], deadline: float) -> None:
        """Serve queries and sleep on new arrivals until ``done()`` (checked under the lock) or ``deadline``."""
        while True:
            self._serve_queries()
            with self._cond:
                if done():
                    return
                left = deadline - time.monotonic()
                if left <= 0:
                    return
                if (self.wire.mode != "lockstep" or self._handler is None
                        or not any(q[2].step <= self.box.step for q in self._queries)):
                    self._cond.wait(min(left, 0.5))
