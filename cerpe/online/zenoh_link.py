"""One robot's link to its team over Zenoh (``eclipse-zenoh``): a ``Link`` for the step engine.

Keys and the link header are in :mod:`cerpe.online.zenoh_wire`. The methods are those
of the engine's link protocol (``begin``, ``broadcast``, ``gather``, ``request``,
``serve``); frames are filed in the engine's :class:`~cerpe.algorithm.link.Mailbox` and
handed out in its :class:`~cerpe.algorithm.link.Inbox`:

* :meth:`ZenohLink.broadcast` puts a frame on ``cerpe/<team>/<robot>/<kind>``;
  the bytes counted are the frame's, once (as :class:`cerpe.transport.Channel`).
* Frames of the team arrive through one subscriber into a per-step store;
  :meth:`ZenohLink.gather` returns when every peer's frame of a step is there or
  the deadline passes. A peer is not waited for when its frame cannot come: it
  left (said bye, or its liveliness token went), it already sent that kind for a
  later step (Zenoh keeps a publisher's order on a key), or it is more than
  ``max_lag_steps`` behind (a robot never seen: from step ``max_lag_steps`` on).
* Image requests are Zenoh queries on the owner's ``image`` key, all of a step
  at once (:meth:`ZenohLink.request`), answered by the owner's queryable. Valid
  queries are queued and answered by the handler given to :meth:`ZenohLink.serve`
  on the thread that calls the link (inside ``begin``, ``gather``, ``request``,
  ``wait_peers``, ``poll``, ``close``), once the owner has begun the query's step,
  so the handler reads the robot's state without locks. One thread
  calls a link.
* Presence: the session and its subscribers open in the constructor (a bad
  endpoint fails there, before a robot loads its models); the liveliness token
  that tells the peers this robot is up is declared by :meth:`ZenohLink.announce`
  (or the first :meth:`ZenohLink.wait_peers`), once the robot is ready to step.

Counting (one entry per event in the next :class:`Inbox`'s ``degradations``;
:meth:`ZenohLink.take_degradations` drains what no inbox delivered yet):
``msg:lost`` (an expected frame or reply not there at the deadline),
``msg:garbled`` (a payload on our keys that does not decode, a missing or foreign
header, a frame whose type is not its key's kind), ``msg:unknown-sender`` (a key
robot not in the roster, a frame whose sender index is not its key robot's),
``msg:image-not-held`` (the owner answered that it no longer holds that image),
``net:peer-lost`` (a peer's session ended without bye, none within ``BYE_GRACE_S``),
``link:protocol-mismatch`` and ``link:team-mismatch`` (once per robot and version/team, with a warning naming
both), ``link:duplicate-robot`` (another session uses this robot's id). Late,
duplicate and far-ahead frames, refused queries and the bytes really sent (frame
+ header) go to :attr:`ZenohLink.stats`.

Every wait has a deadline; a session that cannot open is one
:class:`~cerpe.online.zenoh_session.ZenohSessionError` naming mode and endpoints;
nothing else raises on bad input.
"""
from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import Counter, defaultdict
from typing import Any, Callable, Iterable, Mapping, Sequence

from ..algorithm.link import Inbox, Mailbox, Received, RequestHandler
from ..config import merge_conf
from ..errors import CerpeError
from ..messages import ImageReply, ImageRequest, Message, MessageError, decode
from . import zenoh_session as zs
from . import zenoh_wire as w

log = logging.getLogger(__name__)

#: seconds a peer whose liveliness token went has to say bye before it counts as lost: its bye and
#: the token's end travel apart, and under load the end came first (a peer that closed at once was
#: counted lost about once in 8 runs of the bye test)
BYE_GRACE_S = 0.5

default_conf: dict[str, Any] = {
    "team": "cerpe",              # key chunk shared by the robots of one team
    **zs.default_conf,            # mode, connect, listen, multicast_scouting, zenoh (cerpe.online.zenoh_session)
    "max_lag_steps": 2,           # do not wait for a peer this many steps behind
    "max_ahead_steps": 64,        # frames further ahead of the current step are dropped
    "max_queued_queries": 64,     # image queries waiting to be answered; more are refused ("busy")
}


class ZenohLinkError(CerpeError, ValueError):
    """Bad link configuration, or a Zenoh session that cannot open."""


def _bytes(z: Any) -> bytes | None:
    return None if z is None else z.to_bytes()


class ZenohLink:
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
        self._cond = threading.Condition()   # guards everything below; Zenoh's threads file into it
        self.box = Mailbox(self.robot_id, self.robot_ids, max_ahead_steps=int(self.conf["max_ahead_steps"]))
        self.stats: Counter[str] = self.box.stats
        self._last: dict[str, dict[str, int]] = defaultdict(dict)  # peer -> kind -> highest step received
        self._present: set[str] = set()      # peers whose liveliness token is up
        self._gone: set[str] = set()         # peers that were up and went (bye or lost)
        self._said_bye: set[str] = set()
        self._leaving: dict[str, float] = {}  # peer -> when its token went without a bye (a bye may follow)
        self._reported: set[tuple] = set()   # (what, robot, detail) logged and counted once
        self._queries: list[tuple[Any, str, ImageRequest]] = []  # (query, peer, request), not answered yet
        self._handler: RequestHandler | None = None
        self._token: Any = None
        self._closed = False
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
            self._token = self.session.liveliness().declare_token(w.alive_key(self.team, self.robot_id, self.zid))
        except zenoh.ZError as exc:
            raise ZenohLinkError(f"robot {self.robot_id}: cannot declare its liveliness token: "
                                 f"{zs.first_line(exc)}") from None

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
        payload, attachment = _bytes(sample.payload) or b"", _bytes(sample.attachment)
        with self._cond:
            self.stats["frames_received"] += 1
            self._file(key, payload, attachment)
            self._cond.notify_all()

    def _protocol_mismatch(self, robot: str, tag: str) -> None:
        """Count and name a robot of another link protocol version, once (lock held)."""
        self._once("link:protocol-mismatch", robot, tag,
                   f"robot {robot} speaks cerpe link protocol {tag}, this robot {w.PROTOCOL_TAG}: its frames "
                   f"and requests are ignored (run the same cerpe version on every robot)")

    def _decode(self, robot: str, payload: bytes, attachment: bytes | None) -> Message | None:
        """The message of a payload that carries our header; None, counted, for anything else (lock held)."""
        status = w.header_status(attachment)
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
            if w.header_status(attachment) == "ok":
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
        last = self._last[robot]
        last[kind] = max(last.get(kind, -1), int(msg.step))
        self.box.file(robot, msg, len(payload))  # late, too far ahead, duplicate: counted in stats

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        parsed = w.parse_alive_key(str(sample.key_expr))
        if parsed is None:
            return
        team, robot, tag, zid = parsed
        up = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            if zid != self.zid:
                self._presence(team, robot, tag, up)
            self._cond.notify_all()

    def _presence(self, team: str, robot: str, tag: str, up: bool) -> None:
        if team != self.team:
            if up and robot in self.index_of and robot not in self._present:
                self._once("link:team-mismatch", robot, team,
                           f"robot {robot} is up in team {team!r}, this robot is in team {self.team!r}: "
                           f"they do not hear each other (give both the same --team)")
            return
        if tag != w.PROTOCOL_TAG:
            if up:
                self._protocol_mismatch(robot, tag)
            return
        if robot == self.robot_id:
            if up:
                self._once("link:duplicate-robot", robot, "", f"another Zenoh session announces robot {robot} "
                           f"in team {self.team}: two robots were started with the same id")
            return
        if robot not in self.index_of:
            if up and ("unknown", robot) not in self._reported:
                self._reported.add(("unknown", robot))
                log.info("robot %s: robot %s of team %s is not in the roster %s; ignored",
                         self.robot_id, robot, self.team, self.robot_ids)
            return
        if up:
            if robot in self._leaving:  # back before its bye could come: the old session ended without one
                self._peer_lost(robot)
            if robot in self._gone:  # back after leaving: a new run of that robot
                self._last.pop(robot, None)
                self.box.seen.pop(robot, None)
            self._present.add(robot)
            self._gone.discard(robot)
            self._said_bye.discard(robot)
            log.info("robot %s: robot %s is up", self.robot_id, robot)
        elif robot in self._present:
            self._present.discard(robot)
            self._gone.add(robot)
            if robot not in self._said_bye and not self._closed:
                # the bye and the token's end travel apart: the bye may still come (BYE_GRACE_S)
                self._leaving[robot] = time.monotonic()

    def _peer_lost(self, robot: str) -> None:
        """Count ``robot`` lost: its token went and no bye came within :data:`BYE_GRACE_S` (lock held)."""
        self._leaving.pop(robot, None)
        self._degrade("net:peer-lost")
        log.warning("robot %s: lost robot %s (its Zenoh session ended without bye)", self.robot_id, robot)

    def _settle_leaving(self, peers: Iterable[str] | None = None) -> bool:
        """Count the peers whose grace for a bye is over; True when none of ``peers`` (None: any)
        is still within it (lock held)."""
        now = time.monotonic()
        for robot, t in list(self._leaving.items()):
            if now - t >= BYE_GRACE_S:
                self._peer_lost(robot)
        return not any(p in self._leaving for p in (self._leaving if peers is None else peers))

    def _on_query(self, query: Any) -> None:
        """Check an image query in the Zenoh thread: refuse a bad one at once, queue a good one."""
        payload, attachment = _bytes(query.payload) or b"", _bytes(query.attachment)
        with self._cond:
            reason, peer, req = self._check_query(payload, attachment)
            if reason is None and len(self._queries) >= int(self.conf["max_queued_queries"]):
                reason = "busy"
            if reason is None:
                self._queries.append((query, peer, req))
                self._cond.notify_all()
                return
            self.stats[f"queries_refused_{reason}"] += 1
        with query:
            query.reply_err(w.error_payload(reason))

    def _check_query(self, payload: bytes, attachment: bytes | None) -> tuple[str | None, str, Any]:
        """``(refusal reason or None, peer, request)`` (lock held)."""
        if w.header_status(attachment) == "protocol":
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
        if self._handler is None:
            return
        with self._cond:
            ready = [q for q in self._queries if q[2].step <= self.box.step]
            self._queries = [q for q in self._queries if q[2].step > self.box.step]
        for query, peer, req in ready:
            with query:
                self._answer(query, peer, req)

    def _answer(self, query: Any, peer: str, req: ImageRequest) -> None:
        try:
            reply = self._handler(peer, req)
        except CerpeError as exc:
            log.warning("robot %s: image request of %s for step %d failed: %s", self.robot_id, peer, req.step, exc)
            reply, reason = None, "error"
        else:
            reason = w.NOT_HELD
        with self._cond:
            if reply is None:
                self.stats[f"queries_refused_{reason}"] += 1
            else:
                self.stats["replies_sent"] += 1
                self.stats["wire_bytes_reply"] += len(reply) + len(w.HEADER)
        if reply is None:
            query.reply_err(w.error_payload(reason))
        else:
            query.reply(w.image_key(self.team, self.robot_id), bytes(reply), attachment=w.HEADER)

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

    def broadcast(self, kind: str, frame: bytes) -> int:
        """Put ``frame`` on this robot's ``kind`` key; returns its bytes (counted once)."""
        if kind not in w.BROADCAST_KINDS:
            raise ZenohLinkError(f"robot {self.robot_id}: cannot broadcast kind {kind!r}; "
                                 f"expected one of {w.BROADCAST_KINDS}")
        if not isinstance(frame, (bytes, bytearray)) or not frame:
            raise ZenohLinkError(f"robot {self.robot_id}: empty or non-bytes {kind} frame")
        import zenoh

        try:
            self._pubs[kind].put(bytes(frame), attachment=w.HEADER)
        except zenoh.ZError as exc:  # the session was closed under the robot
            raise ZenohLinkError(f"robot {self.robot_id}: cannot send its {kind}: {zs.first_line(exc)}") from None
        with self._cond:
            self.stats[f"frames_sent_{kind}"] += 1
            self.stats[f"wire_bytes_{kind}"] += len(frame) + len(w.HEADER)
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
        import zenoh

        step = int(step)
        self._check_peers(list(frames), f"request({step})")
        if step != self.box.step:
            self._begin(step)  # the peers' queries are answered in the wait below, once ours are out
        reqs = {}
        for p, frame in frames.items():
            try:
                req = decode(frame)
            except MessageError as exc:
                raise ZenohLinkError(f"robot {self.robot_id}: request frame to {p} does not decode: {exc}") from None
            if not (isinstance(req, ImageRequest) and req.step == step and req.target == self.index_of[p]
                    and req.sender == self.index):
                raise ZenohLinkError(f"robot {self.robot_id}: the frame for {p} is not this robot's image "
                                     f"request of step {step} to {p}: {req}")
            reqs[p] = req
        state = {p: {"ok": [], "err": [], "done": False} for p in frames}

        def on_reply(p: str, reply: Any) -> None:
            with self._cond:
                if reply.ok is not None:
                    state[p]["ok"].append((_bytes(reply.ok.payload) or b"", _bytes(reply.ok.attachment)))
                else:
                    state[p]["err"].append(_bytes(reply.err.payload) or b"")
                self._cond.notify_all()

        def on_done(p: str) -> None:
            with self._cond:
                state[p]["done"] = True
                self._cond.notify_all()

        timeout = max(float(deadline_s), 1e-3)
        deadline = time.monotonic() + timeout
        for p, frame in frames.items():
            handler = zenoh.handlers.Callback(lambda r, p=p: on_reply(p, r), lambda p=p: on_done(p))
            try:
                self.session.get(w.image_key(self.team, p), handler, payload=bytes(frame), attachment=w.HEADER,
                                 timeout=timeout, target=zenoh.QueryTarget.ALL,
                                 consolidation=zenoh.ConsolidationMode.NONE)
            except zenoh.ZError as exc:
                raise ZenohLinkError(f"robot {self.robot_id}: cannot send its image request to {p}: "
                                     f"{zs.first_line(exc)}") from None
            with self._cond:
                self.stats["frames_sent_request"] += 1
                self.stats["wire_bytes_request"] += len(frame) + len(w.HEADER)
        t0 = time.perf_counter()
        self._wait(lambda: all(st["ok"] or st["done"] for st in state.values()), deadline)
        self._serve_queries()  # a peer's query that came in with our last reply: answered now, not next wait
        with self._cond:
            self.stats["wait_s"] += time.perf_counter() - t0
            got = {p: self._check_reply(p, req, state[p]["ok"], state[p]["err"]) for p, req in reqs.items()}
            inbox = self.box.inbox(step, "reply", [])  # the degradations counted so far
        inbox.messages = {p: r for p, r in got.items() if r is not None}
        inbox.sent = {p: len(f) for p, f in frames.items()}
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
            reason = w.parse_error_payload(ours[0])
            self.stats[f"reply_error_{reason}"] += 1
            if reason == w.NOT_HELD:
                self._degrade("msg:image-not-held")
                return None
            log.info("robot %s: robot %s refused the image request of step %d (%s)",
                     self.robot_id, peer, req.step, reason)
        self._degrade("msg:lost")
        return None

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
                if not any(q[2].step <= self.box.step for q in self._queries) or self._handler is None:
                    self._cond.wait(min(left, 0.5))

    def _may_come(self, peer: str, kind: str, step: int) -> bool:
        """Can ``peer``'s ``kind`` frame of ``step`` still arrive? (lock held)"""
        if peer in self._gone:
            return False
        if self._last.get(peer, {}).get(kind, -1) > step:
            return False  # it sent a later one: Zenoh keeps a publisher's order per key
        return self.box.seen.get(peer, -1) >= step - int(self.conf["max_lag_steps"])

    def wait_peers(self, peers: Iterable[str], timeout_s: float) -> list[str]:
        """Wait until every peer's link is up or ``timeout_s`` passes; returns the missing ones."""
        peers = list(peers)
        self.announce()
        self._wait(lambda: all(p in self._present for p in peers), time.monotonic() + max(0.0, float(timeout_s)))
        with self._cond:
            missing = [p for p in peers if p not in self._present]
        if missing:
            hint = ("; found by multicast scouting only: if multicast does not pass on this network, or the "
                    "network came up after this robot started, give endpoints (--connect)"
                    if self.conf["multicast_scouting"] and not self.conf["connect"] else "")
            log.warning("robot %s: robots %s of team %s not up after %.0f s%s", self.robot_id, missing,
                        self.team, timeout_s, hint)
        return missing

    @property
    def present(self) -> set[str]:
        """Peers whose link is up now."""
        with self._cond:
            return set(self._present)

    # ------------------------------------------------------------------ leaving
    def close(self, linger_s: float = 2.0) -> None:
        """Say bye, answer queries until every present peer said bye (at most ``linger_s``), close."""
        if self._closed:
            return
        try:
            if not self.session.is_closed():
                self._pubs[w.BYE].put(b"", attachment=w.HEADER)
                self._wait(lambda: not (self._present - self._said_bye), time.monotonic() + max(0.0, linger_s))
        finally:
            with self._cond:
                self._closed = True
                queries, self._queries = self._queries, []
            import zenoh

            for query, _, _ in queries:
                with query, contextlib.suppress(zenoh.ZError):  # the requester's query may be gone
                    query.reply_err(w.error_payload(w.NOT_HELD))
            self.session.close()

    def __enter__(self) -> "ZenohLink":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close(linger_s=0.0 if exc[0] is not None else 2.0)
