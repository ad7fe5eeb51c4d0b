"""The team's frames by capture stamp (link protocol 2): kept per peer, read at this robot's stamp.

A mixin of :class:`~cerpe.online.zenoh_link.ZenohLink` in ``sync: stamps`` (the methods of the
:class:`~cerpe.algorithm.link.StreamLink`); apart so that the link module stays small. Frames are
filed on Zenoh's threads, under the link's lock: per peer its recent descriptors (with their
stamps), its poses not yet taken, the stamps its frames advance by. A wait ends for a peer when it
is not up, when its newest frame is at this robot's stamp (within half its frame period), or when its
next frame is overdue (no frame for two periods more than the wait: a stalled camera, a robot gone
quiet); at the latest at the deadline. Peers' stamps are mapped into this robot's clock by their
estimated offsets (:class:`~cerpe.online.clock.PeerOffsets`); an offset beyond the tolerance is
counted once per peer and session (``link:clock-offset``).
"""
from __future__ import annotations

import logging
import statistics
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np

from ..algorithm.link import Stamped, StreamInbox
from ..messages import ImageRequest, Message
from . import zenoh_wire as w
from .clock import PeerOffsets, StampClock

if TYPE_CHECKING:  # the attributes the mixin reads, owned by ZenohLink
    from ..algorithm.link import Mailbox

log = logging.getLogger(__name__)

DESCRIPTORS_KEPT = 16  # a peer's recent descriptors kept (the nearest to a stamp is chosen among them)


@dataclass
class PeerStream:
    """What this robot keeps of one peer's frames (lock held)."""

    descriptors: deque = field(default_factory=lambda: deque(maxlen=DESCRIPTORS_KEPT))  # of Stamped (peer stamps)
    poses: list = field(default_factory=list)  # (peer stamp, T_odom_cam) not taken yet
    newest: dict = field(default_factory=dict)  # kind -> (peer stamp, wall arrival) of its newest frame
    stamps: deque = field(default_factory=lambda: deque(maxlen=DESCRIPTORS_KEPT))  # its descriptors' peer stamps
    index: dict = field(default_factory=dict)  # kind -> highest frame index received

    def period_s(self) -> float | None:
        """The median time between its frames (by their stamps), None with fewer than three."""
        st = list(self.stamps)
        gaps = [b - a for a, b in zip(st, st[1:]) if b > a]
        return statistics.median(gaps) if len(gaps) >= 2 else None


class StreamSide:
    """Frames by stamp, for :class:`~cerpe.online.zenoh_link.ZenohLink` in ``sync: stamps``."""

    if TYPE_CHECKING:
        conf: Mapping[str, Any]
        robot_id: str
        team: str
        index: int
        index_of: dict[str, int]
        box: Mailbox
        stats: Counter[str]
        wire: w.Wire
        _cond: threading.Condition
        _present: set[str]
        _closed: bool
        _reported: set[tuple]
        _queries: list[tuple[Any, str, ImageRequest, float]]

        def _once(self, what: str, robot: str, detail: str, message: str) -> None: ...
        def _degrade(self, what: str) -> None: ...
        def _wait(self, done: Callable[[], bool], deadline: float) -> None: ...
        def _send_reply(self, query: Any, reply: bytes | None, reason: str, stamp_s: float) -> None: ...

    def _init_streams(self) -> None:
        self.clock: Any = StampClock()  # the node may give its source's clock instead
        self.offsets = PeerOffsets(float(self.conf["clock_tolerance_s"]))
        self._streams: dict[str, PeerStream] = {}
        self._events: list[tuple[str, str]] = []
        self._frame_handler: Any = None
        self._serving = threading.Thread(target=self._serve_loop, name=f"cerpe-serve-{self.robot_id}", daemon=True)

    # ------------------------------------------------------------------ clocks
    def to_mine(self, peer: str, peer_stamp_s: float) -> float:
        return float(peer_stamp_s) - self.offsets.offset(peer)

    def to_peer(self, peer: str, stamp_s: float) -> float:
        return float(stamp_s) + self.offsets.offset(peer)

    def peer_clock_now(self) -> float | None:
        """The team's stamp clock now as the peers' newest frames say it (their median), None without any."""
        with self._cond:
            got = [(s, t) for p, st in self._streams.items() if p in self._present
                   for s, t in [st.newest.get("clock", (None, None))] if s is not None]
        if not got:
            return None
        now = time.time()
        return statistics.median(s + (now - t) for s, t in got)

    # ------------------------------------------------------------------ filing (Zenoh threads, lock held)
    def _stream_file(self, robot: str, kind: str, msg: Message, nbytes: int, stamp_s: float, clock_s: float) -> None:
        st = self._streams.setdefault(robot, PeerStream())
        now = time.time()
        if clock_s == clock_s:
            st.newest["clock"] = (clock_s, now)
            self.offsets.sample(robot, clock_s, self.clock.now(now))
            off = self.offsets.offset(robot)
            if off:
                self._once("link:clock-offset", robot, "", f"robot {robot}'s stamps are {off:+.3f} s off this "
                           f"robot's clock (more than --clock-tolerance): mapped into it; synchronise the robots' "
                           f"clocks (chrony) for better estimates")
        last = st.index.get(kind, -1)
        if int(msg.step) <= last:
            self.stats["out_of_order" if int(msg.step) < last else "duplicate"] += 1
            return
        st.index[kind] = int(msg.step)
        st.newest[kind] = (stamp_s, now)
        if kind == "descriptor":
            st.descriptors.append(Stamped(msg, nbytes, stamp_s, stamp_s))
            st.stamps.append(stamp_s)
        elif kind == "pose":
            st.poses.append((stamp_s, msg.T_odom_cam))
        else:
            self.stats[f"ignored_{kind}"] += 1

    def _restart_stream(self, robot: str) -> None:
        """``robot`` is up in a new session: its frames and clock start again (lock held)."""
        self._streams.pop(robot, None)
        self.offsets.reset(robot)
        self._reported = {r for r in self._reported if not (r[0] == "link:clock-offset" and r[1] == robot)}

    def take_events(self) -> list[tuple[str, str]]:
        with self._cond:
            out, self._events = self._events, []
            return out

    # ------------------------------------------------------------------ reading (the robot's thread)
    def _settled(self, peer: str, kind: str, stamp_s: float, wait_s: float) -> bool:
        """Is ``peer``'s ``kind`` frame near ``stamp_s`` there, or not to be waited for? (lock held)"""
        if peer not in self._present:
            return True
        st = self._streams.get(peer)
        if st is None or kind not in st.newest:
            return False  # up, nothing yet: its first frame comes soon
        per = st.period_s()
        newest_s, arrived = st.newest[kind]
        if self.to_mine(peer, newest_s) >= stamp_s - 0.5 * (per or 0.0):
            return True
        return per is not None and time.time() - arrived > 2 * per + wait_s  # overdue: stalled or gone quiet

    def descriptors_near(self, peers: Sequence[str], stamp_s: float, wait_s: float, max_age_s: float) -> StreamInbox:
        t0 = time.perf_counter()
        self._wait(lambda: all(self._settled(p, "descriptor", stamp_s, wait_s) for p in peers),
                   time.monotonic() + max(0.0, float(wait_s)))
        with self._cond:
            self.stats["wait_s"] += time.perf_counter() - t0
            out = StreamInbox(present=set(self._present) & set(peers))
            for p in peers:
                st = self._streams.get(p)
                if st is None or not st.descriptors:
                    continue
                near = min(st.descriptors, key=lambda d: abs(self.to_mine(p, d.peer_stamp_s) - stamp_s))
                mine = self.to_mine(p, near.peer_stamp_s)
                if abs(mine - stamp_s) <= max_age_s:
                    out.messages[p] = Stamped(near.message, near.nbytes, mine, near.peer_stamp_s)
                else:
                    self.stats["descriptors_too_old"] += 1
            out.degradations = self.box.inbox(self.box.step, "", []).degradations
            return out

    def wait_poses(self, peers: Sequence[str], stamp_s: float, wait_s: float) -> None:
        t0 = time.perf_counter()
        self._wait(lambda: all(self._settled(p, "pose", stamp_s, wait_s) for p in peers),
                   time.monotonic() + max(0.0, float(wait_s)))
        with self._cond:
            self.stats["wait_s"] += time.perf_counter() - t0

    def poses_since(self, peer: str) -> list[tuple[float, np.ndarray]]:
        with self._cond:
            st = self._streams.get(peer)
            if st is None:
                return []
            out, st.poses = st.poses, []
            return out

    # ------------------------------------------------------------------ serving (a thread of the link's)
    def serve_frames(self, handler: Callable[[str, ImageRequest, float], bytes | None]) -> None:
        self._frame_handler = handler
        if not self._serving.is_alive():
            self._serving.start()

    def _serve_loop(self) -> None:
        """Answer queued image queries as they come, until the link closes."""
        import zenoh

        while True:
            with self._cond:
                while not self._queries and not self._closed:
                    self._cond.wait(0.5)
                if self._closed:
                    return
                query, peer, req, stamp = self._queries.pop(0)
            try:
                reply = self._frame_handler(peer, req, stamp) if self._frame_handler is not None else None
            except Exception as exc:  # noqa: BLE001 -- never let one request end the serving thread
                log.warning("robot %s: image request of %s for frame %d failed: %s", self.robot_id, peer, req.step, exc)
                reply = None
            try:
                with query:
                    self._send_reply(query, reply, "not-held", stamp)
            except zenoh.ZError as exc:  # the requester gave up, or the session is closing
                log.debug("robot %s: reply to %s not sent: %s", self.robot_id, peer, exc)
