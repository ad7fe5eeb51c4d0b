"""One robot of a team, online: drives ONE :class:`~cerpe.algorithm.RobotAgent` over a network.

The phases of a step are those of :meth:`cerpe.algorithm.Team.step`, from one
robot's side (only ``RobotAgent``'s public methods are used):

1. ``begin_step`` and broadcast the :class:`~cerpe.messages.DescriptorMessage`;
2. wait for the peers' descriptors of this step, ``score_descriptor`` each
   (a missing one is scored as None: gate closed, ``descriptor-missing``);
3. send an :class:`~cerpe.messages.ImageRequest` to every peer whose gate is
   open and wait for the :class:`~cerpe.messages.ImageReply`; ``accept_reply``;
4. ``joint_pass``, ``estimate_scale``, ``update_odometry``;
5. broadcast the :class:`~cerpe.messages.PoseMessage`, wait for the peers' poses
   of this step, ``note_pose``;
6. ``relative`` per peer, ``manage_memory``, ``record``.

Image requests of the current step are answered as soon as they arrive, during
any of the waits above (a peer's request can only follow this robot's
descriptor, and the peer waits for the reply before its own pose, for which this
robot is waiting): no phase needs to wait for requests.

Loose synchronisation by step index: each wait ends when every peer's frame of
this step is there, or after ``step_timeout_s``. A peer is not waited for when
it cannot deliver: not connected, already past this step (one ordered stream
per pair: after a frame of step ``t+1`` nothing of step ``t`` comes) or more
than ``max_lag_steps`` behind. So a slow robot costs at most one timeout per
phase and a dead one none; nothing deadlocks.

Counting (added to the robot's :class:`~cerpe.records.RobotRecord`):
``msg:lost`` per expected frame (a peer's descriptor and pose every step, the
reply to each request sent) that did not arrive in time, ``msg:garbled`` per
frame that did not decode, ``msg:unknown-sender`` for a frame whose sender
index is not the connection's robot, ``net:peer-lost`` when a connection to a
peer ends without a bye. Request/reply bytes are counted as
:class:`~cerpe.transport.Channel` counts them (the request when sent, the reply
for its sender; ``bytes_pair`` = request sent + reply received); a frame that
arrives after its step was given up is only counted in :attr:`RobotNode.stats`
(``late``), it already was ``msg:lost``.
"""
from __future__ import annotations

import logging
import time
from collections import Counter, defaultdict
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from ..algorithm import RobotAgent
from ..messages import DescriptorMessage, ImageReply, ImageRequest, Message, PoseMessage
from ..protocols import FrameContext
from ..records import PairRecord, StepResult
from .net import NetTransport, OnlineError

log = logging.getLogger(__name__)

default_conf: dict[str, Any] = {
    "step_timeout_s": 5.0,      # longest wait per phase for the peers' frames of the same step
    "connect_timeout_s": 30.0,  # before step 0: wait this long for every peer to connect
    "max_lag_steps": 2,         # do not wait for a peer this many steps behind (it cannot catch up)
    "max_ahead_steps": 64,      # frames further ahead than this are dropped (counted, ``too_far_ahead``)
    "rate_hz": 0.0,             # replay rate: step t starts no earlier than t / rate_hz after step 0; 0 = free
}

_KIND = {DescriptorMessage: "descriptor", PoseMessage: "pose", ImageRequest: "request", ImageReply: "reply"}


class RobotNode:
    """Runs one robot's agent against its peers on a :class:`~cerpe.online.net.NetTransport`.

    Args:
        agent: this robot's agent (its ``index`` is its wire sender id).
        robot_ids: every robot of the encounter in wire-index order (index = position).
        peers: the robots on the network (a subset of ``robot_ids``); pair records
            are made for these.
        transport: connected (or connecting) transport of this robot.
        conf: overrides of :data:`default_conf`.
    """

    def __init__(self, agent: RobotAgent, robot_ids: Sequence[str], peers: Iterable[str],
                 transport: NetTransport, conf: Mapping[str, Any] | None = None) -> None:
        unknown = set(conf or {}) - set(default_conf)
        if unknown:
            raise OnlineError(f"node conf: unknown keys {sorted(unknown)}; valid: {sorted(default_conf)}")
        self.conf = {**default_conf, **(conf or {})}
        self.agent, self.net = agent, transport
        self.robot_ids = [str(r) for r in robot_ids]
        if agent.robot_id not in self.robot_ids or self.robot_ids.index(agent.robot_id) != agent.index:
            raise OnlineError(f"robot {agent.robot_id}: its index {agent.index} is not its position "
                              f"in {self.robot_ids}")
        peers = set(peers)
        if peers - set(self.robot_ids):
            raise OnlineError(f"robot {agent.robot_id}: peers {sorted(peers - set(self.robot_ids))} are not "
                              f"robots of the encounter {self.robot_ids}")
        self.peers = [r for r in self.robot_ids if r in peers and r != agent.robot_id]
        self.index_of = {r: k for k, r in enumerate(self.robot_ids)}
        self.stats: Counter[str] = Counter()
        self.seen: dict[str, int] = {p: -1 for p in self.peers}  # highest step received from each peer
        self._buf: dict[int, dict[str, dict[str, tuple[Message, int]]]] = defaultdict(lambda: defaultdict(dict))
        self._extra: list[str] = []  # this step's degradations found by the node
        self._sent: Counter[str] = Counter()  # this step's request/reply bytes
        self._t = -1
        self._t0: float | None = None

    # ------------------------------------------------------------------ events
    def _degrade(self, what: str) -> None:
        self._extra.append(what)
        self.stats[what] += 1

    def _pump(self, timeout_s: float = 0.0) -> None:
        """Take the transport's events (waiting up to ``timeout_s`` for one) and file them."""
        for what, peer, info in self.net.next_events(timeout_s):
            if what == "garbled":
                self._degrade("msg:garbled")
                log.debug("robot %s: garbled frame from %s: %s", self.agent.robot_id, peer, info)
            elif what == "down":
                self._degrade("net:peer-lost")
            elif what == "msg":
                self._file(peer, *info)
        self._serve_requests()

    def _file(self, peer: str, msg: Message, nbytes: int) -> None:
        if self.index_of.get(peer) != msg.sender:
            self._degrade("msg:unknown-sender")
            return
        kind = _KIND[type(msg)]
        self.seen[peer] = max(self.seen[peer], int(msg.step))
        if msg.step < self._t:
            if kind == "request":
                self.agent.image_reply(msg)  # counted by the agent as msg:stale-request
            else:
                self.stats["late"] += 1
            return
        if msg.step > self._t + self.conf["max_ahead_steps"]:
            self.stats["too_far_ahead"] += 1
            return
        slot = self._buf[int(msg.step)][kind]
        if peer in slot:
            self.stats["duplicate"] += 1
            return
        slot[peer] = (msg, nbytes)

    def _serve_requests(self) -> None:
        """Answer this step's image requests that have not been answered yet."""
        pending = self._buf.get(self._t, {}).get("request", {})
        for peer, (msg, nbytes) in list(pending.items()):
            if nbytes < 0:
                continue  # answered already
            pending[peer] = (msg, -1)
            reply = self.agent.image_reply(msg)
            if reply is not None:
                frame = reply.encode()
                if self.net.send(peer, frame):
                    self._sent["reply"] += len(frame)

    def _may_come(self, peer: str, t: int) -> bool:
        seen = self.seen[peer]
        return self.net.connected(peer) and seen <= t and seen >= t - self.conf["max_lag_steps"]

    def _wait(self, kind: str, t: int, peers: Sequence[str]) -> dict[str, tuple[Message, int]]:
        """Frames of ``kind`` and step ``t`` from ``peers``; waits as the module docstring says."""
        deadline = time.monotonic() + self.conf["step_timeout_s"]
        t_wait = time.perf_counter()
        while True:
            self._pump()
            have = self._buf.get(t, {}).get(kind, {})
            waiting = [p for p in peers if p not in have and self._may_come(p, t)]
            left = deadline - time.monotonic()
            if not waiting or left <= 0:
                break
            self._pump(min(left, 0.5))
        self.stats["wait_s"] += time.perf_counter() - t_wait
        got = {p: have[p] for p in peers if p in have}
        for p in peers:
            if p not in got:
                self._degrade("msg:lost")
                log.debug("robot %s step %d: no %s from %s", self.agent.robot_id, t, kind, p)
        return got

    # ------------------------------------------------------------------ one step
    def start(self) -> list[str]:
        """Wait (``connect_timeout_s``) until every peer is connected; returns those that are not."""
        missing = self.net.wait_connected(self.conf["connect_timeout_s"])
        if missing:
            log.warning("robot %s: starting without %s (not connected after %.0f s); they may join later",
                        self.agent.robot_id, missing, self.conf["connect_timeout_s"])
        return missing

    def _pace(self, t: int) -> None:
        rate = float(self.conf["rate_hz"])
        if self._t0 is None:
            self._t0 = time.monotonic() - (t / rate if rate > 0 else 0.0)
        if rate > 0:
            delay = self._t0 + t / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def step(self, image: np.ndarray, context: FrameContext, stamp_s: float | None = None) -> StepResult:
        """One step of this robot; returns its pair records (ego = this robot) and its robot record."""
        a, t = self.agent, int(context.step)
        self._pace(t)
        self._t, self._extra, self._sent = t, [], Counter()
        for old in [s for s in self._buf if s < t]:
            del self._buf[old]
        # 1-2. describe, broadcast, gate
        a.begin_step(image, context, stamp_s)
        self.net.broadcast(a.descriptor_frame(a.config.descriptor_dtype))
        got = self._wait("descriptor", t, self.peers)
        scores = {p: a.score_descriptor(p, got[p][0].descriptor if p in got else None) for p in self.peers}
        # 3. requests and replies
        pair_bytes: Counter[str] = Counter()
        asked = []
        for p in self.peers:
            if a.gate_open(p):
                frame = ImageRequest(a.index, t, self.index_of[p]).encode()
                if self.net.send(p, frame):
                    self._sent["request"] += len(frame)
                    pair_bytes[p] += len(frame)
                    asked.append(p)
        for p, (msg, nbytes) in self._wait("reply", t, asked).items():
            pair_bytes[p] += nbytes
            a.accept_reply(p, msg)
        # 4-7. joint pass, scale, odometry, pose broadcast
        a.joint_pass()
        a.estimate_scale()
        a.update_odometry()
        self.net.broadcast(a.pose_frame())
        a.note_pose(a.robot_id, t, a.X)
        for p, (msg, _) in self._wait("pose", t, self.peers).items():
            a.note_pose(p, msg.step, msg.T_odom_cam)
        # 8. relative poses
        pairs = []
        for p in self.peers:
            source, T, reason, anchor_step = a.relative(p)
            pairs.append(PairRecord(step=t, stamp_s=float(t if stamp_s is None else stamp_s), ego=a.robot_id,
                                    other=p, gate_score=float(scores[p]), gate_open=a.gate_open(p), source=source,
                                    T_cj_ci=T, reason=reason, bytes_pair=int(pair_bytes[p]),
                                    anchor_step=anchor_step))
        # 9. memory; late requests of this step are still answered before the record closes
        a.manage_memory()
        self._pump()
        rec = a.record()
        for kind, n in self._sent.items():
            rec.bytes_sent[kind] = rec.bytes_sent.get(kind, 0) + int(n)
        rec.degradations.extend(self._extra)
        return StepResult(step=t, pairs=pairs, robots=[rec])

    def run(self, frames: Iterable[tuple[np.ndarray, FrameContext, float | None]]) -> Iterator[StepResult]:
        """:meth:`start`, then :meth:`step` for every ``(image, context, stamp_s)``."""
        self.start()
        for image, context, stamp in frames:
            yield self.step(image, context, stamp)
