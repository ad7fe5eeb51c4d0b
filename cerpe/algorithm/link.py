"""The link between one robot's step engine and its peers (no transport code here).

A :class:`Link` moves the unchanged :mod:`cerpe.messages` wire frames; the step
engine (:mod:`cerpe.algorithm.engine`) runs the phases of Algorithm 1 over it, the team
in lock-step (every robot at the same step). Two implementations:
:class:`cerpe.algorithm.channel_link.ChannelLink` (a team in one process, over the lossy
:class:`cerpe.transport.Channel`) and :class:`cerpe.online.zenoh_link.ZenohLink` (one robot
per process). A :class:`StreamLink` moves the same frames with their capture stamps, for
robots at their own pace (:mod:`cerpe.algorithm.stamp_engine`; a frame's ``step`` is then its
sender's own frame index). Every wait has a deadline; faults come back counted in an
:class:`Inbox`, never raised.
"""
from __future__ import annotations

import logging
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Callable, Mapping, Protocol, Sequence, runtime_checkable

from ..messages import DescriptorMessage, EstimateMessage, ImageReply, ImageRequest, Message, PoseMessage

log = logging.getLogger(__name__)

#: message class -> kind, as :data:`cerpe.transport.KINDS` names them
KIND_OF: dict[type, str] = {DescriptorMessage: "descriptor", PoseMessage: "pose", ImageRequest: "request",
                            ImageReply: "reply", EstimateMessage: "estimate"}

#: answers an image request: ``(peer, request) -> reply frame`` or None (nothing to send)
RequestHandler = Callable[[str, ImageRequest], "bytes | None"]
#: answers an image request that names a frame by stamp: ``(peer, request, stamp_s) -> reply frame`` or None
#: (not held); called on a thread of the link's, not the robot's
FrameHandler = Callable[[str, ImageRequest, float], "bytes | None"]


@dataclass(frozen=True)
class Received:
    """One decoded frame from a peer and its size on the wire (bytes)."""

    message: Message
    nbytes: int


@dataclass
class Inbox:
    """What one wait brought.

    Attributes:
        messages: peer -> the frame of the asked kind and step it sent.
        degradations: faults the link noticed since its previous answer, one entry
            each (``msg:lost``, ``msg:garbled``, ``msg:unknown-sender``,
            ``net:peer-lost``); the engine books them on this step's record.
        sent: for :meth:`Link.request`: peer -> bytes of the request frame put on
            the wire (absent: not sent).
        gone: asked peers the link knows have left (bye or lost session): nothing more
            will come from them, so the robot stops standing in for their lost frames.
    """

    messages: dict[str, Received] = field(default_factory=dict)
    degradations: list[str] = field(default_factory=list)
    sent: dict[str, int] = field(default_factory=dict)
    gone: set[str] = field(default_factory=set)

    def message(self, peer: str) -> Message | None:
        got = self.messages.get(peer)
        return None if got is None else got.message


@runtime_checkable
class Link(Protocol):
    """One robot's end of the team's medium.

    Frames carry their step. A link files what arrives by (step, kind, sender),
    keeps frames of later steps for later and drops (counts) those of steps it has
    left. It answers image requests through the handler given to :meth:`serve`
    while it waits, so no phase has to wait for requests.
    """

    robot_id: str

    def begin(self, step: int) -> None:
        """This robot is at ``step`` now: its image requests are answered, earlier frames dropped."""
        ...

    def broadcast(self, kind: str, frame: bytes) -> int:
        """Send ``frame`` to every peer; returns the bytes counted for this robot (once, not per peer)."""
        ...

    def gather(self, step: int, kind: str, peers: Sequence[str], deadline_s: float) -> Inbox:
        """The ``kind`` frames of ``step`` from ``peers``: returns when all are there or after ``deadline_s``."""
        ...

    def request(self, step: int, frames: Mapping[str, bytes], deadline_s: float) -> Inbox:
        """Send each peer its image request, wait up to ``deadline_s`` for the replies."""
        ...

    def serve(self, handler: RequestHandler) -> None:
        """Answer image requests from now on with ``handler`` (reply bytes are counted by the handler)."""
        ...


class Mailbox:
    """One robot's received frames filed by (step, kind, sender): the bookkeeping every link shares.

    Frames of the current or a later step (up to ``max_ahead_steps``) are kept
    until taken; of an earlier step they are ``late`` (a request is still handed
    to the handler, which counts it stale). Image requests of the current step are
    answered once each by :meth:`answer` (again when the same request comes again: a
    retry after a lost reply). Counts go to :attr:`stats` and, for the
    degradations, to the next :meth:`inbox`.
    """

    def __init__(self, robot_id: str, robot_ids: Sequence[str], max_ahead_steps: int | None = None) -> None:
        self.robot_id = robot_id
        self.index_of = {str(r): k for k, r in enumerate(robot_ids)}
        self.max_ahead_steps = max_ahead_steps
        self.step = -1
        self.handler: RequestHandler | None = None
        self.stats: Counter[str] = Counter()
        self.seen: dict[str, int] = {}  # highest step received from each peer
        self._buf: dict[int, dict[str, dict[str, Received]]] = defaultdict(lambda: defaultdict(dict))
        self._answered: set[tuple[int, str]] = set()
        self._pending: list[str] = []

    def degrade(self, what: str) -> None:
        self._pending.append(what)
        self.stats[what] += 1

    def begin(self, step: int) -> None:
        self.step = int(step)
        for old in [s for s in self._buf if s < self.step]:
            del self._buf[old]
        self._answered = {a for a in self._answered if a[0] >= self.step}

    def file(self, peer: str, msg: Message, nbytes: int) -> list[tuple[str, bytes]]:
        """Keep one decoded frame; returns ``(peer, reply frame)`` to send for a stale request."""
        if self.index_of.get(peer) != msg.sender:
            self.degrade("msg:unknown-sender")
            return []
        kind = KIND_OF[type(msg)]
        self.seen[peer] = max(self.seen.get(peer, -1), int(msg.step))
        if msg.step < self.step:
            if kind == "request" and self.handler is not None:
                reply = self.handler(peer, msg)  # counted stale by the handler
                return [] if reply is None else [(peer, reply)]
            self.stats["late"] += 1
            return []
        if self.max_ahead_steps is not None and msg.step > self.step + self.max_ahead_steps:
            self.stats["too_far_ahead"] += 1
            return []
        slot = self._buf[int(msg.step)][kind]
        if peer in slot and kind == "request":  # asked again (its reply was lost): answered again
            self._answered.discard((int(msg.step), peer))
            self.stats["request_repeated"] += 1
        elif peer in slot:
            self.stats["duplicate"] += 1
            return []
        slot[peer] = Received(msg, int(nbytes))
        return []

    def answer(self) -> list[tuple[str, bytes]]:
        """Replies ``(peer, frame)`` to this step's requests not answered yet."""
        out = []
        if self.handler is None:
            return out
        for peer, got in self._buf.get(self.step, {}).get("request", {}).items():
            if (self.step, peer) in self._answered:
                continue
            self._answered.add((self.step, peer))
            reply = self.handler(peer, got.message)
            if reply is not None:
                out.append((peer, reply))
        return out

    def have(self, step: int, kind: str) -> dict[str, Received]:
        return self._buf.get(step, {}).get(kind, {})

    def inbox(self, step: int, kind: str, peers: Sequence[str]) -> Inbox:
        """The ``kind`` frames of ``step`` from ``peers`` and the degradations noticed since the last inbox."""
        have = self.have(step, kind)
        got = {p: have[p] for p in peers if p in have}
        out, self._pending = Inbox(got, self._pending), []
        return out


@dataclass(frozen=True)
class Stamped:
    """A peer's frame with its capture stamp: ``stamp_s`` in this robot's clock, ``peer_stamp_s`` as the
    peer stamped it (what an image request names); ``message.step`` is the peer's own frame index."""

    message: Message
    nbytes: int
    stamp_s: float
    peer_stamp_s: float


@dataclass
class StreamInbox:
    """What a wait by stamp brought: per peer the frame nearest the asked stamp, the degradations noticed
    since the last answer, and the peers up now."""

    messages: dict[str, Stamped] = field(default_factory=dict)
    degradations: list[str] = field(default_factory=list)
    present: set[str] = field(default_factory=set)


@runtime_checkable
class StreamLink(Protocol):
    """One robot's end of the team when every robot runs at its own pace (frames carry capture stamps).

    No global step: a robot broadcasts each frame it processes with its stamp, reads each peer's
    frame nearest its own stamp, and asks a peer for the image of one of its frames by that
    frame's stamp. Waits end when what can still come has come, at the latest at their deadline.
    """

    robot_id: str

    def broadcast(self, kind: str, frame: bytes, stamp_s: float | None = None) -> int:
        """Send ``frame`` (of this robot's frame captured at ``stamp_s``); returns its bytes (counted once)."""
        ...

    def descriptors_near(self, peers: Sequence[str], stamp_s: float, wait_s: float, max_age_s: float) -> StreamInbox:
        """Each peer's descriptor nearest ``stamp_s`` (this robot's clock) and at most ``max_age_s`` from it,
        after waiting at most ``wait_s`` for one that may still come nearer."""
        ...

    def wait_poses(self, peers: Sequence[str], stamp_s: float, wait_s: float) -> None:
        """Wait at most ``wait_s`` until each peer's poses reach ``stamp_s`` (or cannot any more)."""
        ...

    def poses_since(self, peer: str) -> list[tuple[float, object]]:
        """``(stamp in the peer's clock, T_odom_cam)`` of the peer's poses received since the last call."""
        ...

    def to_peer(self, peer: str, stamp_s: float) -> float:
        """A stamp of this robot's clock in ``peer``'s."""
        ...

    def request_frames(self, asks: Mapping[str, tuple[bytes, float]], deadline_s: float) -> Inbox:
        """Send each peer its image request ``(frame, peer stamp of the frame asked)``; replies within ``deadline_s``."""
        ...

    def serve_frames(self, handler: FrameHandler) -> None:
        """Answer image requests by stamp with ``handler`` from now on (on a thread of the link's)."""
        ...

    def take_events(self) -> list[tuple[str, str]]:
        """``(peer, event)`` since the last call: ``up``, ``restarted`` (a new session), ``gone``."""
        ...

    def take_degradations(self) -> list[str]:
        """Degradations noticed since the last answer that no inbox handed out."""
        ...
