"""One robot's link to its team over Zenoh (``eclipse-zenoh``): the ``Link`` of the step engine.

Keys and the link header are in :mod:`cerpe.online.zenoh_wire`. What the link does:

* :meth:`ZenohLink.broadcast` puts a frame on ``cerpe/<team>/<robot>/<kind>``;
  the bytes counted are the frame's, once (as :class:`cerpe.transport.Channel`).
* Frames of the team arrive through one subscriber into a per-step inbox;
  :meth:`ZenohLink.gather` returns when every peer's frame of each kind of a step
  is there or the deadline passes. A peer is not waited for when its frame cannot
  come: it left (said bye, or its liveliness token went), it already sent that
  kind for a later step (Zenoh keeps a publisher's order on a key), or it is more
  than ``max_lag_steps`` behind (or never appeared after step ``max_lag_steps``).
* Image requests are Zenoh queries on the owner's ``image`` key, answered by its
  queryable. Queries are queued and answered by the handler given to
  :meth:`ZenohLink.serve` on the thread that calls the link (in ``gather``,
  ``request``, ``wait_peers``, ``poll``, ``close``), so the handler may read the
  robot's state without locks, exactly as the TCP node did.

Counting (one entry per event in the next :class:`Inbox`'s ``degradations``;
:meth:`ZenohLink.take_degradations` drains what no gather delivered yet):
``msg:lost`` (an expected frame not there at the deadline, a request with no
reply), ``msg:garbled`` (a payload on our keys that does not decode, a missing
or foreign header, a frame whose type is not its key's kind),
``msg:unknown-sender`` (a key robot not in the roster, a frame whose sender index
is not its key robot's), ``msg:image-not-held`` (the owner answered that it no
longer holds that image), ``net:peer-lost`` (a peer's session ended without
bye), ``link:protocol-mismatch`` and ``link:team-mismatch`` (once per robot and
version/team, with a warning naming both). Late, duplicate and far-ahead frames
and the bytes really sent (frame + header) go to :attr:`ZenohLink.stats`.

Every wait has a deadline; a session that cannot open is one
:class:`ZenohLinkError` naming the endpoints; nothing else raises on bad input.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

from ..config import merge_conf
from ..errors import CerpeError
from ..messages import ImageReply, ImageRequest, Message, MessageError, decode
from . import zenoh_wire as w

log = logging.getLogger(__name__)

default_conf: dict[str, Any] = {
    "team": "cerpe",              # key chunk shared by the robots of one team
    "mode": "peer",               # "peer" (default) or "client" (needs a router in "connect")
    "connect": [],                # Zenoh endpoints to dial, e.g. ["tcp/10.0.0.2:7447"]
    "listen": [],                 # endpoints to listen on; [] = Zenoh's default (peer: any port)
    "multicast_scouting": True,   # find peers on the LAN by UDP multicast
    "max_lag_steps": 2,           # do not wait for a peer this many steps behind
    "max_ahead_steps": 64,        # frames further ahead of the current step are dropped
    "max_queued_queries": 64,     # image queries waiting for serve(); more are refused ("busy")
    "zenoh": None,                # extra Zenoh config, {json5 path: value}, applied last
}

_MODES = ("peer", "client")


class ZenohLinkError(CerpeError, ValueError):
    """Bad link configuration, or a Zenoh session that cannot open."""


@dataclass
class Inbox:
    """What :meth:`ZenohLink.gather` got for one step.

    Attributes:
        step: the step gathered.
        messages: sender robot id -> kind -> decoded message of that step.
        nbytes: sender robot id -> kind -> frame bytes received.
        degradations: counted problems since the previous gather (``msg:lost`` ...).
    """

    step: int
    messages: dict[str, dict[str, Message]] = field(default_factory=dict)
    nbytes: dict[str, dict[str, int]] = field(default_factory=dict)
    degradations: list[str] = field(default_factory=list)

    def get(self, sender: str, kind: str) -> Message | None:
        return self.messages.get(sender, {}).get(kind)


def zenoh_config(conf: Mapping[str, Any]) -> Any:
    """A ``zenoh.Config`` from the link conf (mode, endpoints, scouting, extra keys)."""
    import zenoh

    if conf["mode"] not in _MODES:
        raise ZenohLinkError(f"zenoh mode {conf['mode']!r}: expected one of {_MODES}")
    entries: list[tuple[str, Any]] = [("mode", conf["mode"]),
                                      ("scouting/multicast/enabled", bool(conf["multicast_scouting"]))]
    for what in ("connect", "listen"):
        eps = conf[what]
        if isinstance(eps, str) or not all(isinstance(e, str) for e in eps):
            raise ZenohLinkError(f"--{what}: expected a list of endpoints like tcp/10.0.0.2:7447, got {eps!r}")
        if eps:
            entries.append((f"{what}/endpoints", list(eps)))
    if conf["mode"] == "client" and not conf["connect"]:
        raise ZenohLinkError("zenoh mode 'client' needs a router endpoint in --connect (e.g. tcp/10.0.0.1:7447)")
    extra = conf.get("zenoh") or {}
    if not isinstance(extra, Mapping):
        raise ZenohLinkError(f"link conf 'zenoh': expected {{json5 path: value}}, got {type(extra).__name__}")
    entries += list(extra.items())
    zc = zenoh.Config()
    for key, value in entries:
        try:
            zc.insert_json5(str(key), json.dumps(value))
        except zenoh.ZError as exc:
            raise ZenohLinkError(f"zenoh config {key} = {value!r}: {_first_line(exc)}") from None
    return zc


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text.split(" at /")[0]  # zenoh appends the Rust source location


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
        ZenohLinkError: a bad name or option, or a session that cannot open.
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
        self.stats: Counter[str] = Counter()
        self._cond = threading.Condition()
        self._buf: dict[int, dict[str, dict[str, tuple[Message, int]]]] = defaultdict(lambda: defaultdict(dict))
        self._last: dict[str, dict[str, int]] = defaultdict(dict)  # peer -> kind -> highest step received
        self._floor = 0                      # lowest step still filed
        self._pending: list[str] = []        # degradations not yet handed out
        self._present: set[str] = set()      # peers whose liveliness token is up
        self._gone: set[str] = set()         # peers that were up and went (bye or lost)
        self._said_bye: set[str] = set()
        self._reported: set[tuple] = set()   # (what, robot, detail) logged and counted once
        self._queries: list[Any] = []
        self._handler: Callable[[bytes], bytes | None] | None = None
        self._closed = False
        zc = zenoh_config(self.conf)
        try:
            self.session = zenoh.open(zc)
        except zenoh.ZError as exc:
            raise ZenohLinkError(
                f"robot {self.robot_id}: Zenoh session cannot open (mode {self.conf['mode']}, "
                f"listen {self.conf['listen'] or 'default'}, connect {self.conf['connect'] or 'none'}): "
                f"{_first_line(exc)}") from None
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
            # the token last: a peer that sees it can reach this robot's subscriber and queryable
            self._token = self.session.liveliness().declare_token(w.alive_key(self.team, self.robot_id, self.zid))
        except zenoh.ZError as exc:
            self.session.close()
            raise ZenohLinkError(f"robot {self.robot_id}: Zenoh declarations failed: {_first_line(exc)}") from None

    # ------------------------------------------------------------------ counting
    def _degrade(self, what: str) -> None:
        """Queue one degradation (caller holds the lock)."""
        self._pending.append(what)
        self.stats[what] += 1

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
            out, self._pending = self._pending, []
        return out

    # ------------------------------------------------------------------ receiving (Zenoh threads)
    def _on_sample(self, sample: Any) -> None:
        key = w.parse_data_key(str(sample.key_expr))
        payload, attachment = _bytes(sample.payload) or b"", _bytes(sample.attachment)
        with self._cond:
            self.stats["frames_received"] += 1
            self._file(key, payload, attachment)
            self._cond.notify_all()

    def _file(self, key: tuple[str, str, str] | None, payload: bytes, attachment: bytes | None) -> None:
        if key is None:
            self._degrade("msg:garbled")
            return
        _, robot, kind = key
        status = w.header_status(attachment)
        if status == "protocol":
            self._once("link:protocol-mismatch", robot, w.header_tag(attachment),
                       f"robot {robot} speaks cerpe link protocol {w.header_tag(attachment)}, this robot "
                       f"{w.PROTOCOL_TAG}: its frames are ignored (run the same cerpe version on every robot)")
            self.stats["frames_foreign_protocol"] += 1
            return
        if status != "ok":
            self._degrade("msg:garbled")
            log.debug("robot %s: frame on %s without a cerpe link header", self.robot_id, kind)
            return
        if robot == self.robot_id:
            self._once("link:duplicate-robot", robot, "", f"another Zenoh session publishes as robot {robot} "
                       f"in team {self.team}: two robots were started with the same id")
            return
        if robot not in self.index_of:
            self._degrade("msg:unknown-sender")
            log.debug("robot %s: frame from robot %r, not in the roster %s", self.robot_id, robot, self.robot_ids)
            return
        if kind == w.BYE:
            self._said_bye.add(robot)
            self._gone.add(robot)
            return
        try:
            msg = decode(payload)
        except MessageError as exc:
            self._degrade("msg:garbled")
            log.debug("robot %s: garbled %s frame from %s: %s", self.robot_id, kind, robot, exc)
            return
        if w.KIND_OF_TYPE.get(msg.TYPE) != kind:
            self._degrade("msg:garbled")
            log.debug("robot %s: a %s frame on %s's %s key", self.robot_id, type(msg).__name__, robot, kind)
            return
        if msg.sender != self.index_of[robot]:
            self._degrade("msg:unknown-sender")
            log.debug("robot %s: frame on %s's key says sender index %d", self.robot_id, robot, msg.sender)
            return
        step = int(msg.step)
        last = self._last[robot]
        last[kind] = max(last.get(kind, -1), step)
        if step < self._floor:
            self.stats["late"] += 1
        elif step > self._floor + int(self.conf["max_ahead_steps"]):
            self.stats["too_far_ahead"] += 1
        elif robot in self._buf[step][kind]:
            self.stats["duplicate"] += 1
        else:
            self._buf[step][kind][robot] = (msg, len(payload))

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
                self._once("link:protocol-mismatch", robot, tag,
                           f"robot {robot} speaks cerpe link protocol {tag}, this robot {w.PROTOCOL_TAG}: "
                           f"its frames are ignored (run the same cerpe version on every robot)")
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
            if robot in self._gone:  # back after leaving: a new run of that robot
                self._last.pop(robot, None)
            self._present.add(robot)
            self._gone.discard(robot)
            self._said_bye.discard(robot)
            log.info("robot %s: robot %s is up", self.robot_id, robot)
        elif robot in self._present:
            self._present.discard(robot)
            self._gone.add(robot)
            if robot not in self._said_bye and not self._closed:
                self._degrade("net:peer-lost")
                log.warning("robot %s: lost robot %s (its Zenoh session ended without bye)",
                            self.robot_id, robot)

    def _on_query(self, query: Any) -> None:
        with self._cond:
            if len(self._queries) >= int(self.conf["max_queued_queries"]):
                self.stats["queries_refused_busy"] += 1
                with query:
                    query.reply_err(w.error_payload("busy"))
                return
            self._queries.append(query)
            self._cond.notify_all()

    # ------------------------------------------------------------------ serving (caller's thread)
    def serve(self, handler: Callable[[bytes], bytes | None]) -> None:
        """Answer image requests with ``handler(request_frame) -> reply_frame | None``.

        The handler is called on the thread that calls the link, inside its
        waits; None means "image not held" (the requester counts
        ``msg:image-not-held``). A :class:`CerpeError` from it is logged and
        answered as an error; other exceptions propagate to the caller.
        """
        self._handler = handler

    def poll(self, timeout_s: float = 0.0) -> None:
        """Answer image queries for ``timeout_s`` (0: those waiting now); use it instead of sleeping."""
        self._wait(lambda: False, time.monotonic() + max(0.0, float(timeout_s)))

    def _serve_queries(self) -> None:
        if self._handler is None:
            return
        with self._cond:
            queries, self._queries = self._queries, []
        for query in queries:
            with query:
                self._answer(query)

    def _answer(self, query: Any) -> None:
        payload, status = _bytes(query.payload) or b"", w.header_status(_bytes(query.attachment))
        reason = None
        if status != "ok":
            reason = status
        else:
            try:
                msg = decode(payload)
            except MessageError:
                msg = None
            if not isinstance(msg, ImageRequest):
                reason = "garbled"
            elif msg.target != self.index:
                reason = "wrong-target"
        if reason is None:
            try:
                reply = self._handler(payload)
            except CerpeError as exc:
                log.warning("robot %s: image request of step %d failed: %s", self.robot_id, msg.step, exc)
                reply, reason = None, "error"
            if reply is not None:
                query.reply(w.image_key(self.team, self.robot_id), reply, attachment=w.HEADER)
                self.stats["replies_sent"] += 1
                self.stats["wire_bytes_reply"] += len(reply) + len(w.HEADER)
                return
            reason = reason or w.NOT_HELD
        self.stats[f"queries_refused_{reason}"] += 1
        query.reply_err(w.error_payload(reason))

    # ------------------------------------------------------------------ sending
    def broadcast(self, kind: str, frame: bytes) -> int:
        """Put ``frame`` on this robot's ``kind`` key; returns its bytes (counted once)."""
        if kind not in w.BROADCAST_KINDS:
            raise ZenohLinkError(f"robot {self.robot_id}: cannot broadcast kind {kind!r}; "
                                 f"expected one of {w.BROADCAST_KINDS}")
        if not isinstance(frame, (bytes, bytearray)) or not frame:
            raise ZenohLinkError(f"robot {self.robot_id}: empty or non-bytes {kind} frame")
        self._pubs[kind].put(bytes(frame), attachment=w.HEADER)
        with self._cond:
            self.stats[f"frames_sent_{kind}"] += 1
            self.stats[f"wire_bytes_{kind}"] += len(frame) + len(w.HEADER)
        return len(frame)

    def request(self, peer: str, frame: bytes, deadline_s: float) -> tuple[bytes | None, int]:
        """Ask ``peer`` for an image; returns ``(reply frame or None, request bytes sent)``.

        The reply is returned only if it decodes as an :class:`ImageReply` of
        ``peer`` for the request's step; anything else is None and counted
        (``msg:lost`` for no reply in ``deadline_s``, ``msg:image-not-held``,
        ``msg:garbled``, ``msg:unknown-sender``). Image queries that reach this
        robot meanwhile are answered.
        """
        import zenoh

        if peer not in self.index_of or peer == self.robot_id:
            raise ZenohLinkError(f"robot {self.robot_id}: cannot request from {peer!r}; peers: "
                                 f"{[r for r in self.robot_ids if r != self.robot_id]}")
        try:
            req = decode(frame)
        except MessageError as exc:
            raise ZenohLinkError(f"robot {self.robot_id}: request frame to {peer} does not decode: {exc}") from None
        if not isinstance(req, ImageRequest):
            raise ZenohLinkError(f"robot {self.robot_id}: request() takes an ImageRequest frame, "
                                 f"got {type(req).__name__}")
        state: dict[str, Any] = {"ok": [], "err": [], "done": False}

        def on_reply(reply: Any) -> None:
            with self._cond:
                if reply.ok is not None:
                    state["ok"].append((_bytes(reply.ok.payload) or b"", _bytes(reply.ok.attachment)))
                else:
                    state["err"].append(_bytes(reply.err.payload) or b"")
                self._cond.notify_all()

        def on_done() -> None:
            with self._cond:
                state["done"] = True
                self._cond.notify_all()

        timeout = max(float(deadline_s), 1e-3)
        deadline = time.monotonic() + timeout
        self.session.get(w.image_key(self.team, peer), zenoh.handlers.Callback(on_reply, on_done),
                         payload=bytes(frame), attachment=w.HEADER, timeout=timeout,
                         target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE)
        with self._cond:
            self.stats["frames_sent_request"] += 1
            self.stats["wire_bytes_request"] += len(frame) + len(w.HEADER)
        self._wait(lambda: bool(state["ok"]) or state["done"], deadline)
        with self._cond:
            reply = self._check_reply(peer, req, state["ok"], state["err"])
        return reply, len(frame)

    def _check_reply(self, peer: str, req: ImageRequest, oks: list, errs: list) -> bytes | None:
        """The first valid reply, or None with the reason counted (lock held)."""
        if len(oks) > 1:
            self.stats["extra_replies"] += len(oks) - 1
        for payload, attachment in oks[:1]:
            status = w.header_status(attachment)
            if status == "protocol":
                self._once("link:protocol-mismatch", peer, w.header_tag(attachment),
                           f"robot {peer} replied with link protocol {w.header_tag(attachment)}, this robot "
                           f"{w.PROTOCOL_TAG}: reply ignored")
                return None
            try:
                msg = decode(payload) if status == "ok" else None
            except MessageError:
                msg = None
            if not isinstance(msg, ImageReply) or msg.step != req.step:
                self._degrade("msg:garbled")
                return None
            if msg.sender != self.index_of[peer]:
                self._degrade("msg:unknown-sender")
                return None
            self.stats["replies_received"] += 1
            return payload
        ours = [e for e in errs if e[:2] == w.MAGIC]
        if ours:  # the owner answered with a reason; Zenoh's own errors (timeout) carry no header
            reason = w.parse_error_payload(ours[0])
            self.stats[f"reply_error_{reason}"] += 1
            if reason == w.NOT_HELD:
                self._degrade("msg:image-not-held")
                return None
            if reason == "protocol":
                self._once("link:protocol-mismatch", peer, "?", f"robot {peer} refused a request as another "
                           f"link protocol (this robot {w.PROTOCOL_TAG})")
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
                if not self._queries or self._handler is None:
                    self._cond.wait(min(left, 0.5))

    def _may_come(self, peer: str, kind: str, step: int) -> bool:
        """Can ``peer``'s ``kind`` frame of ``step`` still arrive? (lock held)"""
        if peer in self._gone:
            return False
        last = self._last.get(peer, {})
        if last.get(kind, -1) > step:
            return False  # it sent a later one: Zenoh keeps a publisher's order per key
        return max(last.values(), default=-1) >= step - int(self.conf["max_lag_steps"])

    def gather(self, step: int, kinds: Iterable[str], peers: Sequence[str], deadline_s: float) -> Inbox:
        """This step's frames of ``kinds`` from ``peers``, waiting at most ``deadline_s``.

        Returns as soon as every peer's frame of every kind is there or cannot
        come (see the module docstring). Each missing one is a ``msg:lost``.
        Frames of earlier steps are forgotten; later ones are kept.
        """
        step, kinds = int(step), tuple(kinds)
        unknown = [p for p in peers if p not in self.index_of or p == self.robot_id]
        if unknown or any(k not in w.BROADCAST_KINDS for k in kinds):
            raise ZenohLinkError(f"robot {self.robot_id}: gather({step}, {kinds}, {list(peers)}): peers must be "
                                 f"other robots of {self.robot_ids}, kinds among {w.BROADCAST_KINDS}")
        with self._cond:
            if step < self._floor:
                raise ZenohLinkError(f"robot {self.robot_id}: gather of step {step} after step {self._floor}")
            self._floor = step
            for old in [s for s in self._buf if s < step]:
                del self._buf[old]

        def complete() -> bool:
            have = self._buf.get(step, {})
            return all(p in have.get(k, {}) or not self._may_come(p, k, step) for p in peers for k in kinds)

        t0 = time.perf_counter()
        self._wait(complete, time.monotonic() + max(0.0, float(deadline_s)))
        with self._cond:
            self.stats["wait_s"] += time.perf_counter() - t0
            inbox = Inbox(step)
            have = self._buf.get(step, {})
            for p in peers:
                for k in kinds:
                    got = have.get(k, {}).get(p)
                    if got is None:
                        self._degrade("msg:lost")
                        continue
                    inbox.messages.setdefault(p, {})[k] = got[0]
                    inbox.nbytes.setdefault(p, {})[k] = got[1]
            inbox.degradations, self._pending = self._pending, []
        return inbox

    def wait_peers(self, peers: Iterable[str], timeout_s: float) -> list[str]:
        """Wait until every peer's link is up or ``timeout_s`` passes; returns the missing ones."""
        peers = list(peers)
        self._wait(lambda: all(p in self._present for p in peers), time.monotonic() + max(0.0, float(timeout_s)))
        with self._cond:
            return [p for p in peers if p not in self._present]

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
            self._pubs[w.BYE].put(b"", attachment=w.HEADER)
            self._wait(lambda: not (self._present - self._said_bye), time.monotonic() + max(0.0, linger_s))
        finally:
            with self._cond:
                self._closed = True
            self.session.close()

    def __enter__(self) -> "ZenohLink":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close(linger_s=0.0 if exc[0] is not None else 2.0)
