"""A :class:`~cerpe.algorithm.link.Link` over the TCP :class:`~cerpe.online.net.NetTransport`.

Loose synchronisation by step index: a wait ends when every peer's frame of the
step is there, or at its deadline. A peer is not waited for when it cannot
deliver: not connected, already past the step (one ordered stream per pair:
after a frame of step ``t+1`` nothing of step ``t`` comes) or more than
``max_lag_steps`` behind. So a slow robot costs at most one deadline per wait and
a dead one none. Image requests of the current step are answered during any
wait (a peer's request can only follow this robot's descriptor, and the peer
waits for the reply before its own pose, for which this robot is waiting).

Counted (in the next :class:`~cerpe.algorithm.link.Inbox` and in :attr:`TcpLink.stats`):
``msg:lost`` per expected frame missing at the deadline (a peer's descriptor and
pose every step, the reply to each request sent), ``msg:garbled`` per frame that
does not decode, ``msg:unknown-sender``, ``net:peer-lost`` when a connection ends
without a bye. Only in :attr:`TcpLink.stats`: ``late`` (a frame of a step already
given up, which was counted lost), ``duplicate``, ``too_far_ahead``, ``wait_s``.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from typing import Mapping, Sequence

from ..algorithm.link import Inbox, Mailbox, RequestHandler
from .net import NetTransport

log = logging.getLogger(__name__)


class TcpLink:
    """This robot's end of the team network.

    Args:
        net: this robot's transport (connected, or connecting).
        robot_ids: every robot of the encounter in wire-index order.
        max_lag_steps: do not wait for a peer this many steps behind.
        max_ahead_steps: frames further ahead are dropped (``too_far_ahead``).
    """

    def __init__(self, net: NetTransport, robot_ids: Sequence[str], max_lag_steps: int = 2,
                 max_ahead_steps: int = 64) -> None:
        self.net, self.robot_id = net, net.robot_id
        self.max_lag_steps = int(max_lag_steps)
        self.box = Mailbox(self.robot_id, robot_ids, max_ahead_steps=int(max_ahead_steps))

    @property
    def stats(self) -> Counter[str]:
        return self.box.stats

    def _pump(self, timeout_s: float = 0.0) -> None:
        """Take the transport's events (waiting up to ``timeout_s`` for one), file them, answer requests."""
        replies = []
        for what, peer, info in self.net.next_events(timeout_s):
            if what == "garbled":
                self.box.degrade("msg:garbled")
                log.debug("robot %s: garbled frame from %s: %s", self.robot_id, peer, info)
            elif what == "down":
                self.box.degrade("net:peer-lost")
            elif what == "msg":
                replies += self.box.file(peer, *info)
        for peer, frame in replies + self.box.answer():
            self.net.send(peer, frame)

    def _may_come(self, peer: str, step: int) -> bool:
        seen = self.box.seen.get(peer, -1)
        return self.net.connected(peer) and step - self.max_lag_steps <= seen <= step

    def _wait(self, step: int, kind: str, peers: Sequence[str], deadline_s: float) -> Inbox:
        deadline = time.monotonic() + deadline_s
        t_wait = time.perf_counter()
        while True:
            self._pump()
            have = self.box.have(step, kind)
            waiting = [p for p in peers if p not in have and self._may_come(p, step)]
            left = deadline - time.monotonic()
            if not waiting or left <= 0:
                break
            self._pump(min(left, 0.5))
        self.box.stats["wait_s"] += time.perf_counter() - t_wait
        for p in peers:
            if p not in self.box.have(step, kind):
                self.box.degrade("msg:lost")
                log.debug("robot %s step %d: no %s from %s", self.robot_id, step, kind, p)
        return self.box.inbox(step, kind, peers)

    # ------------------------------------------------------------------ Link
    def begin(self, step: int) -> None:
        self.box.begin(step)
        self._pump()

    def broadcast(self, kind: str, frame: bytes) -> int:
        self.net.broadcast(frame)
        return len(frame)

    def gather(self, step: int, kind: str, peers: Sequence[str], deadline_s: float) -> Inbox:
        return self._wait(step, kind, peers, deadline_s)

    def request(self, step: int, frames: Mapping[str, bytes], deadline_s: float) -> Inbox:
        sent = {p: len(f) for p, f in frames.items() if self.net.send(p, f)}
        inbox = self._wait(step, "reply", list(sent), deadline_s)
        inbox.sent = sent
        return inbox

    def serve(self, handler: RequestHandler) -> None:
        self.box.handler = handler

