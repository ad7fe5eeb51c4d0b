"""Who of the team is up: liveliness tokens, byes, peers lost without one, and waiting for peers.

A mixin of :class:`~cerpe.online.zenoh_link.ZenohLink` (it reads the link's roster and keeps its
peer sets, under the link's lock); apart so that the link module stays the engine's link protocol.
A peer whose token goes has :data:`BYE_GRACE_S` to say bye before it counts as ``net:peer-lost``.
A peer is up while a token of it is (one per Zenoh session); a token of a new session while the
robot was gone, or beside the old one (a process restarted before its old session was noticed
gone), is a new run of that robot: event ``restarted`` (``up`` the first time, ``gone`` on leaving).
"""
from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any, Callable, Iterable, Mapping

from . import zenoh_wire as w

if TYPE_CHECKING:  # the attributes the mixin reads, owned by ZenohLink
    from ..algorithm.link import Mailbox

log = logging.getLogger(__name__)

#: seconds a peer whose liveliness token went has to say bye before it counts as lost. Its bye and
#: the token's end travel apart, and under load the end can come first.
BYE_GRACE_S = 0.5


class PresenceSide:
    """Peers up, gone and lost, for :class:`~cerpe.online.zenoh_link.ZenohLink`."""

    if TYPE_CHECKING:
        conf: Mapping[str, Any]
        robot_id: str
        robot_ids: list[str]
        index_of: dict[str, int]
        team: str
        zid: str
        box: Mailbox
        _cond: threading.Condition
        _last: dict[str, dict[str, int]]
        _present: set[str]
        _gone: set[str]
        _said_bye: set[str]
        _leaving: dict[str, float]
        _reported: set[tuple]
        _closed: bool
        _sessions: dict[str, set[str]]
        _events: list[tuple[str, str]]
        wire: w.Wire

        def announce(self) -> None: ...
        def _restart_stream(self, robot: str) -> None: ...
        def _degrade(self, what: str) -> None: ...
        def _once(self, what: str, robot: str, detail: str, message: str) -> None: ...
        def _protocol_mismatch(self, robot: str, tag: str) -> None: ...
        def _wait(self, done: Callable[[], bool], deadline: float) -> None: ...

    # ------------------------------------------------------------------ tokens and byes (Zenoh threads)
    def _on_alive(self, sample: Any) -> None:
        import zenoh

        parsed = w.parse_alive_key(str(sample.key_expr))
        if parsed is None:
            return
        team, robot, tag, zid = parsed
        up = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            if zid != self.zid:
                self._presence(team, robot, tag, up, zid)
            self._cond.notify_all()

    def _presence(self, team: str, robot: str, tag: str, up: bool, zid: str = "") -> None:
        if team != self.team:
            if up and robot in self.index_of and robot not in self._present:
                self._once("link:team-mismatch", robot, team,
                           f"robot {robot} is up in team {team!r}, this robot is in team {self.team!r}: "
                           f"they do not hear each other (give both the same --team)")
            return
        if tag != self.wire.tag:
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
        sessions = self._sessions.setdefault(robot, set())
        if up:
            if zid in sessions:
                return
            again = robot in self._gone or bool(sessions)  # back after leaving, or beside its old session
            sessions.add(zid)
            if robot in self._leaving:  # back before its bye could come: the old session ended without one
                self._peer_lost(robot)
            if again:  # a new run of that robot
                self._last.pop(robot, None)
                self.box.seen.pop(robot, None)
                if self.wire.mode == "stamps":
                    self._restart_stream(robot)
            self._events.append((robot, "restarted" if again else "up"))
            self._present.add(robot)
            self._gone.discard(robot)
            self._said_bye.discard(robot)
            log.info("robot %s: robot %s is up%s", self.robot_id, robot, " again (a new session)" if again else "")
        else:
            sessions.discard(zid)
            if sessions or robot not in self._present:
                return  # a newer session of it is up: only its old one ended
            if robot not in self._gone:  # (a bye came first: said already)
                self._events.append((robot, "gone"))
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

    # ------------------------------------------------------------------ waiting for peers
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
