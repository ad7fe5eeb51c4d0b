"""One robot's link to its team over Zenoh (``eclipse-zenoh``): a ``Link`` or a ``StreamLink``.

Keys and the link header are in :mod:`cerpe.online.zenoh_wire`. ``sync: stamps`` (what ``cerpe
online`` runs) makes it the :class:`~cerpe.algorithm.link.StreamLink` of robots at their own pace
(the methods of :mod:`cerpe.online.zenoh_stream`, image requests answered on a serving thread).
``sync: lockstep`` makes it the engine's lock-step :class:`~cerpe.algorithm.link.Link` (``begin``,
``broadcast``, ``gather``, ``request``, ``serve``), which reproduces ``cerpe run``; frames are then
filed in the engine's :class:`~cerpe.algorithm.link.Mailbox` and handed out in its
:class:`~cerpe.algorithm.link.Inbox`:

* :meth:`ZenohLink.broadcast` puts a frame on ``cerpe/<team>/<robot>/<kind>``;
  the bytes counted are the frame's, once (as :class:`cerpe.transport.Channel`).
* Frames of the team arrive through one subscriber into a per-step store.
  :meth:`ZenohLink.gather` returns when every peer's frame of a step is there or
  the deadline passes. A peer is not waited for when its frame cannot come. That is
  when it left (said bye, or its liveliness token went), or already sent that kind for
  a later step (Zenoh keeps a publisher's order on a key). It is also when the peer is
  more than ``max_lag_steps`` behind (a robot never seen: from step ``max_lag_steps`` on).
* Image requests are Zenoh queries on the owner's ``image`` key, all of a step
  at once (:meth:`ZenohLink.request`), answered by the owner's queryable. Valid
  queries are queued and answered by the handler given to :meth:`ZenohLink.serve`.
  It runs on the thread that calls the link (inside ``begin``, ``gather``, ``request``,
  ``wait_peers``, ``poll``, ``close``), once the owner has begun the query's step.
  So the handler reads the robot's state without locks. One thread calls a link.
* Presence: the session and its subscribers open in the constructor, so a bad
  endpoint fails there, before a robot loads its models. The liveliness token
  that tells the peers this robot is up is declared by :meth:`ZenohLink.announce`
  (or the first :meth:`ZenohLink.wait_peers`), once the robot is ready to step.

Counting: one entry per event in the next :class:`Inbox`'s ``degradations``;
:meth:`ZenohLink.take_degradations` drains what no inbox delivered yet.

* ``msg:lost``: an expected frame or reply not there at the deadline;
* ``msg:garbled``: a payload on our keys that does not decode, a missing or foreign
  header, a frame whose type is not its key's kind;
* ``msg:unknown-sender``: a key robot not in the roster, a frame whose sender index
  is not its key robot's;
* ``msg:image-not-held``: the owner answered that it no longer holds that image;
* ``net:peer-lost``: a peer's session ended without bye, none within ``BYE_GRACE_S``;
* ``link:protocol-mismatch`` and ``link:team-mismatch``: once per robot and
  version/team, with a warning naming both;
* ``link:duplicate-robot``: another session uses this robot's id;
* ``link:clock-offset`` (by stamps): a peer's clock is off this robot's beyond ``clock_tolerance_s``.

Late, duplicate and far-ahead frames, refused queries and the bytes really sent (frame
+ header) go to :attr:`ZenohLink.stats`.

Every wait has a deadline. A session that cannot open is one
:class:`~cerpe.online.zenoh_session.ZenohSessionError` naming mode and endpoints;
nothing else raises on bad input.
"""
from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import Counter, defaultdict
from typing import Any, Mapping, Sequence

from ..algorithm.link import Inbox, Mailbox, Received, RequestHandler
from ..config import merge_conf
from ..errors import CerpeError
from ..messages import ImageReply, ImageRequest, MessageError, decode
from . import zenoh_session as zs
from . import zenoh_wire as w
from .zenoh_presence import PresenceSide
from .zenoh_receive import ReceiveSide
from .zenoh_serve import ServeSide
from .zenoh_stream import StreamSide

log = logging.getLogger(__name__)

default_conf: dict[str, Any] = {
    "team": "cerpe",              # key chunk shared by the robots of one team
    **zs.default_conf,            # mode, connect, listen, multicast_scouting, zenoh (cerpe.online.zenoh_session)
    "max_lag_steps": 2,           # do not wait for a peer this many steps behind
    "max_ahead_steps": 64,        # frames further ahead of the current step are dropped
    "max_queued_queries": 64,     # image queries waiting to be answered; more are refused ("busy")
    "sync": "lockstep",           # lockstep: the team's step (reproduces cerpe run); stamps: each robot at its pace
    "clock_tolerance_s": 0.05,    # stamps: a peer's clock offset beyond this is mapped (and counted once)
}


class ZenohLinkError(CerpeError, ValueError):
    """Bad link configuration, or a Zenoh session that cannot open."""


class ZenohLink(ReceiveSide, PresenceSide, ServeSide, StreamSide):
    """This robot's end of the team, over one Zenoh session.

    Args:
        robot_id: this robot.
        robot_ids: every robot of the team in wire-index order (a frame's sender
            index is its robot's position here).
        conf: overrides of :data:`default_conf` (strict: unknown keys are errors).

    Raises:
        ZenohLinkError, ZenohWireError, ZenohSessionError: a bad roster, name or
            option, or a session that cannot open.
    """

    def __init__(self, robot_id: str, robot_ids: Sequence[str], conf: Mapping[str, Any] | None = None) -> None:
        import zenoh

        self.conf = merge_conf(default_conf, conf, "zenoh link conf")
        self.team = w.check_chunk(self.conf["team"], "--team")
        self.robot_id = w.check_chunk(robot_id, "robot id")
        self.robot_ids = [w.check_chunk(r, "robot id") for r in robot_ids]
        if len(set(self.robot_ids)) != len(self.robot_ids) or self.robot_id not in self.robot_ids:
            raise ZenohLinkError(f"robot {self.robot_id}: the roster {self.robot_ids} must list each robot "
                                 f"once and include this one")
        self.index_of = {r: k for k, r in enumerate(self.robot_ids)}
        self.index = self.index_of[self.robot_id]
        self.wire = w.Wire(self.conf["sync"])
        if not float(self.conf["clock_tolerance_s"]) >= 0:
            raise ZenohLinkError(f"--clock-tolerance must be >= 0, got {self.conf['clock_tolerance_s']!r}")
        self._cond = threading.Condition()   # guards everything below; Zenoh's threads file into it
        self.box = Mailbox(self.robot_id, self.robot_ids, max_ahead_steps=int(self.conf["max_ahead_steps"]))
        self.stats: Counter[str] = self.box.stats
        self._last: dict[str, dict[str, int]] = defaultdict(dict)  # peer -> kind -> highest step received
        self._present: set[str] = set()      # peers whose liveliness token is up
        self._gone: set[str] = set()         # peers that were up and went (bye or lost)
        self._said_bye: set[str] = set()
        self._leaving: dict[str, float] = {}  # peer -> when its token went without a bye (a bye may follow)
        self._reported: set[tuple] = set()   # (what, robot, detail) logged and counted once
        self._sessions: dict[str, set[str]] = {}  # peer -> Zenoh ids of its sessions up
        self._queries: list[tuple[Any, str, ImageRequest, float]] = []  # (query, peer, request, stamp), not answered
        self._handler: RequestHandler | None = None
        self._token: Any = None
        self._closed = False
        self._init_streams()
        self.session = zs.open_session({k: self.conf[k] for k in zs.default_conf}, f"robot {self.robot_id}")
        try:
            self.zid = str(self.session.zid())
            remote = zenoh.Locality.REMOTE
            self._sub = self.session.declare_subscriber(w.team_keys(self.team), self._on_sample,
                                                        allowed_origin=remote)
            self._queryable = self.session.declare_queryable(w.image_key(self.team, self.robot_id),
                                                             self._on_query, complete=True)
            self._pubs = {k: self.session.declare_publisher(w.data_key(self.team, self.robot_id, k))
                          for k in (*w.BROADCAST_KINDS, w.BYE)}
            self._alive_sub = self.session.liveliness().declare_subscriber(w.ALIVE_ALL, self._on_alive,
                                                                           history=True)
        except zenoh.ZError as exc:
            self.session.close()
            raise ZenohLinkError(f"robot {self.robot_id}: Zenoh declarations failed: {zs.first_line(exc)}") from None

    def announce(self) -> None:
        """Declare this robot's liveliness token: its peers see it up (and start) from now on.

        Separate from opening, so that a robot can open its session first (a bad
        endpoint fails before models load) and announce itself once it is ready to
        step; :meth:`wait_peers` announces if this was not called.
        """
        import zenoh

        if self._token is not None:
            return
        try:
            self._token = self.session.liveliness().declare_token(w.alive_key(self.team, self.robot_id, self.zid,
                                                                              self.wire.tag))
        except zenoh.ZError as exc:
            raise ZenohLinkError(f"robot {self.robot_id}: cannot declare its liveliness token: "
                                 f"{zs.first_line(exc)}") from None

    # ------------------------------------------------------------------ the Link
    def begin(self, step: int) -> None:
        """This robot is at ``step``: earlier frames are dropped, requests up to ``step`` answered."""
        self._begin(int(step))
        self._serve_queries()

    def _begin(self, step: int) -> None:
        with self._cond:
            if step < self.box.step:
                raise ZenohLinkError(f"robot {self.robot_id}: step {step} begun after step {self.box.step}")
            self.box.begin(step)

    def clock_now(self) -> float | None:
        """This robot's stamp clock now (by stamps; None in lock-step or before its first frame)."""
        return self.clock.now() if self.wire.mode == "stamps" else None

    def broadcast(self, kind: str, frame: bytes, stamp_s: float | None = None) -> int:
        """Put ``frame`` (of this robot's frame stamped ``stamp_s``) on its ``kind`` key; returns its bytes
        (counted once)."""
        if kind not in w.BROADCAST_KINDS:
            raise ZenohLinkError(f"robot {self.robot_id}: cannot broadcast kind {kind!r}; "
                                 f"expected one of {w.BROADCAST_KINDS}")
        if not isinstance(frame, (bytes, bytearray)) or not frame:
            raise ZenohLinkError(f"robot {self.robot_id}: empty or non-bytes {kind} frame")
        import zenoh

        try:
            self._pubs[kind].put(bytes(frame), attachment=self.wire.attachment(stamp_s, self.clock_now()))
        except zenoh.ZError as exc:  # the session was closed under the robot
            raise ZenohLinkError(f"robot {self.robot_id}: cannot send its {kind}: {zs.first_line(exc)}") from None
        with self._cond:
            self.stats[f"frames_sent_{kind}"] += 1
            self.stats[f"wire_bytes_{kind}"] += len(frame) + self.wire.size
        return len(frame)

    def gather(self, step: int, kind: str, peers: Sequence[str], deadline_s: float) -> Inbox:
        """The ``kind`` frames of ``step`` from ``peers``: returns when all are there or cannot come,
        or after ``deadline_s``; each missing one is a ``msg:lost``."""
        step = int(step)
        self._check_peers(peers, f"gather({step}, {kind!r})")
        if kind not in w.BROADCAST_KINDS:
            raise ZenohLinkError(f"robot {self.robot_id}: gather of kind {kind!r}; expected one of "
                                 f"{w.BROADCAST_KINDS}")
        if step != self.box.step:
            self.begin(step)

        def complete() -> bool:
            have = self.box.have(step, kind)
            return all(p in have or not self._may_come(p, kind, step) for p in peers) and self._settle_leaving(peers)

        t0 = time.perf_counter()
        self._wait(complete, time.monotonic() + max(0.0, float(deadline_s)))
        with self._cond:
            self._settle_leaving()
            self.stats["wait_s"] += time.perf_counter() - t0
            have = self.box.have(step, kind)
            for p in peers:
                if p not in have:
                    self._degrade("msg:lost")
            inbox = self.box.inbox(step, kind, peers)
            inbox.gone = {p for p in peers if p in self._gone}
            return inbox

    def request(self, step: int, frames: Mapping[str, bytes], deadline_s: float) -> Inbox:
        """Send each peer its image request (a Zenoh query), wait up to ``deadline_s`` for the replies.

        ``messages`` holds each reply that decodes as that peer's
        :class:`ImageReply` of ``step``; each other peer is counted once
        (``msg:lost`` for no reply in time, ``msg:image-not-held``,
        ``msg:garbled``, ``msg:unknown-sender``). ``sent``: request bytes per peer.
        """
        step = int(step)
        if step != self.box.step:
            self._begin(step)  # the peers' queries are answered in the wait below, once ours are out
        return self._ask({p: (self._request_of(p, f, step), f, None) for p, f in frames.items()}, deadline_s)

    def request_frames(self, asks: Mapping[str, tuple[bytes, float]], deadline_s: float) -> Inbox:
        """By stamps: each peer's image request ``(frame, the peer's stamp of the frame it names)`` as a
        Zenoh query; replies within ``deadline_s``, counted as :meth:`request` counts them."""
        return self._ask({p: (self._request_of(p, f, None), f, float(s)) for p, (f, s) in asks.items()}, deadline_s)

    def _request_of(self, peer: str, frame: bytes, step: int | None) -> ImageRequest:
        """The request ``frame`` to ``peer`` decoded, checked to be this robot's (of ``step`` when given)."""
        self._check_peers([peer], "request")
        try:
            req = decode(frame)
        except MessageError as exc:
            raise ZenohLinkError(f"robot {self.robot_id}: request frame to {peer} does not decode: {exc}") from None
        if not (isinstance(req, ImageRequest) and (step is None or req.step == step)
                and req.target == self.index_of[peer] and req.sender == self.index):
            raise ZenohLinkError(f"robot {self.robot_id}: the frame for {peer} is not this robot's image request "
                                 f"to {peer}{'' if step is None else f' of step {step}'}: {req}")
        return req

    def _ask(self, reqs: Mapping[str, tuple[ImageRequest, bytes, float | None]], deadline_s: float) -> Inbox:
        """Send the queries ``peer -> (request, frame, stamp)``, wait for the replies, check and count them."""
        import zenoh

        state = {p: {"ok": [], "err": [], "done": False} for p in reqs}

        def on_reply(p: str, reply: Any) -> None:
            with self._cond:
                if reply.ok is not None:
                    state[p]["ok"].append((w.as_bytes(reply.ok.payload) or b"", w.as_bytes(reply.ok.attachment)))
                else:
                    state[p]["err"].append(w.as_bytes(reply.err.payload) or b"")
                self._cond.notify_all()

        def on_done(p: str) -> None:
            with self._cond:
                state[p]["done"] = True
                self._cond.notify_all()

        timeout = max(float(deadline_s), 1e-3)
        deadline = time.monotonic() + timeout
        for p, (_, frame, stamp) in reqs.items():
            handler = zenoh.handlers.Callback(lambda r, p=p: on_reply(p, r), lambda p=p: on_done(p))
            try:
                self.session.get(w.image_key(self.team, p), handler, payload=bytes(frame),
                                 attachment=self.wire.attachment(stamp, self.clock_now()), timeout=timeout,
                                 target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE)
            except zenoh.ZError as exc:
                raise ZenohLinkError(f"robot {self.robot_id}: cannot send its image request to {p}: "
                                     f"{zs.first_line(exc)}") from None
            with self._cond:
                self.stats["frames_sent_request"] += 1
                self.stats["wire_bytes_request"] += len(frame) + self.wire.size
        t0 = time.perf_counter()
        self._wait(lambda: all(st["ok"] or st["done"] for st in state.values()), deadline)
        self._serve_queries()  # a peer's query that came in with our last reply: answered now, not next wait
        with self._cond:
            self.stats["wait_s"] += time.perf_counter() - t0
            got = {p: self._check_reply(p, req, state[p]["ok"], state[p]["err"]) for p, (req, _, _) in reqs.items()}
            inbox = self.box.inbox(self.box.step, "reply", [])  # the degradations counted so far
        inbox.messages = {p: r for p, r in got.items() if r is not None}
        inbox.sent = {p: len(f) for p, (_, f, _) in reqs.items()}
        return inbox

    def _check_peers(self, peers: Sequence[str], what: str) -> None:
        bad = [p for p in peers if p not in self.index_of or p == self.robot_id]
        if bad:
            raise ZenohLinkError(f"robot {self.robot_id}: {what}: {bad} are not other robots of {self.robot_ids}")

    def _check_reply(self, peer: str, req: ImageRequest, oks: list, errs: list) -> Received | None:
        """The first reply if it is valid, else None with the reason counted (lock held)."""
        if len(oks) > 1:
            self.stats["extra_replies"] += len(oks) - 1
        for payload, attachment in oks[:1]:
            msg = self._decode(peer, payload, attachment)
            if msg is None:
                return None
            if not isinstance(msg, ImageReply) or msg.step != req.step:
                self._degrade("msg:garbled")
                return None
            if msg.sender != self.index_of[peer]:
                self._degrade("msg:unknown-sender")
                return None
            self.stats["replies_received"] += 1
            return Received(msg, len(payload))
        ours = [e for e in errs if e[:2] == w.MAGIC]
        if ours:  # the owner answered with a reason; Zenoh's own errors (timeout) carry no header
            reason = self.wire.parse_error_payload(ours[0])
            self.stats[f"reply_error_{reason}"] += 1
            if reason == w.NOT_HELD:
                self._degrade("msg:image-not-held")
                return None
            log.info("robot %s: robot %s refused the image request of step %d (%s)",
                     self.robot_id, peer, req.step, reason)
        self._degrade("msg:lost")
        return None

    def _may_come(self, peer: str, kind: str, step: int) -> bool:
        """Can ``peer``'s ``kind`` frame of ``step`` still arrive? (lock held)"""
        if peer in self._gone:
            return False
        if self._last.get(peer, {}).get(kind, -1) > step:
            return False  # it sent a later one: Zenoh keeps a publisher's order per key
        return self.box.seen.get(peer, -1) >= step - int(self.conf["max_lag_steps"])

    # ------------------------------------------------------------------ leaving
    def close(self, linger_s: float = 2.0) -> None:
        """Say bye, answer queries until every present peer said bye (at most ``linger_s``), close."""
        if self._closed:
            return
        try:
            if not self.session.is_closed():
                self._pubs[w.BYE].put(b"", attachment=self.wire.attachment(None, self.clock_now()))
                self._wait(lambda: not (self._present - self._said_bye), time.monotonic() + max(0.0, linger_s))
        finally:
            with self._cond:
                self._closed = True
                queries, self._queries = self._queries, []
                self._cond.notify_all()
            import zenoh

            for query, _, _, _ in queries:
                with query, contextlib.suppress(zenoh.ZError):  # the requester's query may be gone
                    query.reply_err(self.wire.error_payload(w.NOT_HELD))
            if self._serving.is_alive():
                self._serving.join(2.0)
            self.session.close()

    def __enter__(self) -> "ZenohLink":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close(linger_s=0.0 if exc[0] is not None else 2.0)
