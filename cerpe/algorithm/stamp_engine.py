"""ONE robot's step of Algorithm 1 at its own pace, by capture stamps, over a :class:`~cerpe.algorithm.link.StreamLink`.

The phases are :class:`~cerpe.algorithm.engine.StepEngine`'s; what differs is whom they meet. There is
no team step: each robot processes the frames it takes (its newest) and numbers them itself. At its
frame of stamp ``s``:

* the gate scores each peer's descriptor nearest ``s`` (the link waits briefly for one that may still
  come nearer; at most ``stamps.max_descriptor_age_s`` away). A peer that is not up is ``peer-absent``;
* an image request names that peer frame by its index and stamp; the peer answers from the frames it
  holds (:class:`~cerpe.algorithm.frame_ring.FrameRing`), on a thread of its link. A reply already got
  for that frame is used again without asking;
* each peer's odometry pose at ``s`` is interpolated from its pose stream (kept in the peer's clock, ``s``
  mapped into it by the link), or extrapolated within ``stamps.max_extrapolation_s``; beyond, the
  pair propagates nothing at this frame (``pose:too-far``). A direct estimate through a peer view of
  another instant is moved by the peer's motion between the two (:meth:`RobotAgent.set_collab_motion`);
* a peer that comes back in a new session (its odometry restarted) is forgotten (``net:peer-restarted``).

Nothing waits for a full team or for a peer that left; a wait for a slower peer lasts at most ``wait_s``
and at most :data:`WAIT_FRACTION` of the robot's compute time per frame.
"""
from __future__ import annotations

import time
from collections import Counter
from typing import Any, Iterable, Sequence

import numpy as np

from ..geometry import se3_inverse
from ..messages import ImageReply, ImageRequest
from ..protocols import FrameContext
from ..records import StepResult
from ..stamped_poses import SAME_STAMP_S, StampedPoses
from .agent import RobotAgent
from .config import AlgorithmError
from .engine import team_roster
from .frame_ring import FrameRing
from .link import Stamped, StreamLink

#: a peer's poses kept (its stream at this robot)
POSES_KEPT = 256
#: a wait for a peer's descriptor or pose lasts at most this fraction of the robot's own compute time per frame
#: (the median of its recent frames, waits left out), so a slower peer never slows it by more than that
WAIT_FRACTION = 0.5


class StampEngine:
    """Runs one robot's :class:`RobotAgent` at its own pace over a :class:`StreamLink`, one frame per :meth:`step`.

    Args:
        agent: the robot (its ``index`` is its position in ``robot_ids``, the wire sender id).
        link: its end of the team; the engine's :class:`FrameRing` answers image requests through it.
        robot_ids: every robot of the team in wire-index order.
        peers: the robots it exchanges with and makes pair records for (default: all others).
        wait_s: the longest wait for a peer's descriptor or pose near this frame's stamp (and at most
            :data:`WAIT_FRACTION` of the robot's compute time per frame).
        reply_wait_s: the longest wait for the replies to this frame's image requests.
        keep_frames: own frames held for image requests.
    """

    def __init__(self, agent: RobotAgent, link: StreamLink, robot_ids: Sequence[str],
                 peers: Iterable[str] | None = None, wait_s: float = 0.5, reply_wait_s: float = 2.0,
                 keep_frames: int = 8) -> None:
        if agent.config.messages.share_estimates:
            raise AlgorithmError(f"robot {agent.robot_id}: messages.share_estimates needs the robots in lock-step "
                                 f"(cerpe online --lockstep)")
        self.agent, self.link, self.wait_s, self.reply_wait_s = agent, link, float(wait_s), float(reply_wait_s)
        self.robot_ids, self.peers, self.index_of = team_roster(agent, robot_ids, peers)
        self.stamps = agent.config.stamps
        self.ring = FrameRing(agent.index, agent.config.messages, keep_frames)
        self.poses = {p: StampedPoses(POSES_KEPT) for p in self.peers}
        self._replies: dict[str, tuple[int, float, ImageReply]] = {}  # peer -> (its frame, its stamp, reply)
        self.events: list[tuple[float, str, str]] = []  # (this robot's frame stamp, peer, up | restarted | gone)
        self._compute: list[float] = []  # the recent frames' step times without the waits (s), the newest last
        self._waited = 0.0  # this frame's waits so far (s)
        self.pose_stats: Counter[str] = Counter()  # how each peer pose at a frame was had (StampedPoses.at's how)
        link.serve_frames(self.ring.reply)

    def _wait_s(self) -> float:
        """This frame's waits: ``wait_s``, at most :data:`WAIT_FRACTION` of the robot's compute time per frame."""
        c = self._compute[-9:]
        return self.wait_s if len(c) < 2 else min(self.wait_s, WAIT_FRACTION * float(np.median(c)))

    def _timed(self, call: Any, *args: Any) -> Any:
        """``call(*args)``, a wait of the link's: its time is left out of the robot's compute time."""
        t0 = time.perf_counter()
        try:
            return call(*args)
        finally:
            self._waited += time.perf_counter() - t0

    def _book(self, degradations: Iterable[str]) -> None:
        for what in degradations:
            self.agent.degrade(what)

    def _events(self, stamp_s: float) -> None:
        for peer, event in self.link.take_events():
            if peer not in self.poses:
                continue
            self.events.append((stamp_s, peer, event))
            if event == "restarted":  # its odometry starts again from identity: the pair starts afresh
                self.agent.forget_peer(peer)
                self.poses[peer].clear()
                self._replies.pop(peer, None)
                self.agent.degrade("net:peer-restarted")
            elif event == "gone":
                self.agent.peer_gone(peer)
                self._replies.pop(peer, None)

    def step(self, image: np.ndarray, context: FrameContext, stamp_s: float, T_odom_cam: np.ndarray | None = None,
             degradations: Iterable[str] = ()) -> StepResult:
        """This robot's frame ``context.step`` captured at ``stamp_s`` (this robot's clock, seconds).

        ``T_odom_cam``: the robot's own odometry at the frame (None: the backbone's ego-motion);
        ``degradations``: what the frame's input counted (dropped frames, a stall...), booked on its record.
        """
        a, link, t, stamp_s = self.agent, self.link, int(context.step), float(stamp_s)
        t0, self._waited, wait_s = time.perf_counter(), 0.0, self._wait_s()
        a.begin_step(image, context, stamp_s)
        self._book(degradations)
        self._events(stamp_s)
        a.count_sent("descriptor", link.broadcast("descriptor", a.descriptor_frame(a.config.messages.descriptor_dtype),
                                                  stamp_s))
        self.ring.hold(t, stamp_s, a.cur.image, context.intrinsics)
        got = self._timed(link.descriptors_near, self.peers, stamp_s, wait_s, float(self.stamps.max_descriptor_age_s))
        self._book(got.degradations)
        chosen: dict[str, Stamped] = {}
        for p in self.peers:
            near = got.messages.get(p)
            if near is None and p not in got.present:
                a.peer_absent(p)
                continue
            a.score_descriptor(p, None if near is None else near.message)
            if near is not None:
                chosen[p] = near
        asked = [p for p in chosen if a.wants_image(p)]
        replies, sent = self._images(asked, chosen)
        for p in asked:
            if p in replies:
                a.accept_reply(p, replies[p], same_step=False)
            else:
                a.reply_missing(p)
        a.joint_pass()
        a.estimate_scale()
        a.update_odometry(T_odom_cam)
        a.count_sent("pose", link.broadcast("pose", a.pose_frame(), stamp_s))
        self.ring.set_pose(t, a.X)
        a.note_pose(a.robot_id, t, a.X)
        self._timed(link.wait_poses, [p for p in self.peers if p in got.present], stamp_s, wait_s)
        for p in self.peers:
            self._peer_pose(p, t, stamp_s, chosen[p].stamp_s if p in replies else None, p in got.present)
        pairs = [a.pair_record(p, sent.get(p, 0)) for p in self.peers]
        a.manage_memory()
        a.count_sent("reply", self.ring.take_bytes())
        self._book(link.take_degradations())
        self._compute = (self._compute + [time.perf_counter() - t0 - self._waited])[-9:]
        return StepResult(step=t, pairs=pairs, robots=[a.record()])

    def _images(self, asked: Sequence[str], chosen: dict[str, Stamped]) -> tuple[dict[str, ImageReply], dict[str, int]]:
        """The replies to this frame's requests (a reply already got for the same peer frame is used again)
        and the bytes per peer (request and reply) put on the wire for them."""
        a, got, sent, frames = self.agent, {}, {}, {}
        for p in asked:
            near, kept = chosen[p], self._replies.get(p)
            if kept is not None and kept[0] == near.message.step and abs(kept[1] - near.peer_stamp_s) <= SAME_STAMP_S:
                got[p] = kept[2]
            else:
                frames[p] = (ImageRequest(a.index, int(near.message.step), self.index_of[p]).encode(), near.peer_stamp_s)
        for attempt in range(1 + int(a.config.messages.request_retries)):
            todo = {p: f for p, f in frames.items() if p not in got}
            if not todo:
                break
            inbox = self._timed(self.link.request_frames, todo, self.reply_wait_s)
            self._book(inbox.degradations)
            for p in todo if attempt else ():
                a.degrade("msg:request-retried")
            for p, n in inbox.sent.items():
                a.count_sent("request", n)
                sent[p] = sent.get(p, 0) + n
            for p, rec in inbox.messages.items():
                reply, near = rec.message, chosen[p]
                got[p] = reply
                sent[p] = sent.get(p, 0) + rec.nbytes
                self._replies[p] = (int(reply.step), near.peer_stamp_s, reply)
                if reply.T_odom_cam is not None and reply.pose_step == reply.step:  # the pose of that very frame
                    self.poses[p].add(near.peer_stamp_s, reply.T_odom_cam)
        return got, sent

    def _peer_pose(self, p: str, t: int, stamp_s: float, view_stamp_s: float | None, present: bool) -> None:
        """Peer ``p``'s pose at this frame (noted, or unknown), and its motion since its received view."""
        a, conf = self.agent, self.stamps
        for s, X in self.link.poses_since(p):
            self.poses[p].add(s, X)
        gap, ext = float(conf.max_pose_gap_s), float(conf.max_extrapolation_s)
        X_now, how = self.poses[p].at(self.link.to_peer(p, stamp_s), gap, ext)
        self.pose_stats[how] += 1
        if X_now is None:
            a.pose_unknown(p)
            if present and how in ("too-far", "gap"):
                a.degrade("pose:too-far")
        else:
            a.note_pose(p, t, X_now)
        if view_stamp_s is None or abs(view_stamp_s - stamp_s) <= SAME_STAMP_S:
            return
        X_view, _ = self.poses[p].at(self.link.to_peer(p, view_stamp_s), gap, ext)
        if X_now is None or X_view is None:
            a.degrade("pose:peer-motion-unknown")
            a.set_collab_motion(p, None)
        else:
            a.set_collab_motion(p, se3_inverse(X_now) @ X_view)
