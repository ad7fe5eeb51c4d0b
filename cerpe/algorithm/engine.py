"""The phases of ONE robot's step of Algorithm 1, written once, over a :class:`~cerpe.algorithm.link.Link`.

:meth:`StepEngine.step` is a generator: it yields at its two wait points (before
it gathers the peers' descriptors, before it gathers their poses) and returns the
step's :class:`~cerpe.records.StepResult`. A team in one process advances all its
engines to the same wait point before any goes on (:func:`drive`), so every robot's
frames are on the channel before anyone reads, in a fixed order: deterministic. A
robot process resumes at once; there its link's ``gather`` blocks until the peers'
frames are there or the deadline passes.
"""
from __future__ import annotations

from typing import Generator, Iterable, Sequence

import numpy as np

from ..messages import ImageRequest
from ..protocols import FrameContext
from ..records import StepResult
from .agent import RobotAgent
from .config import AlgorithmError
from .link import Inbox, Link

StepRun = Generator[str, None, StepResult]


def team_roster(agent: RobotAgent, robot_ids: Sequence[str],
                peers: Iterable[str] | None) -> tuple[list[str], list[str], dict[str, int]]:
    """``(robot ids, the peers the agent exchanges with, robot -> wire index)``; an
    :class:`AlgorithmError` when the agent's index is not its position or a peer is not in the team."""
    ids = [str(r) for r in robot_ids]
    if agent.robot_id not in ids or ids.index(agent.robot_id) != agent.index:
        raise AlgorithmError(f"robot {agent.robot_id}: its index {agent.index} is not its position in {ids}")
    wanted = set(ids if peers is None else peers)
    if wanted - set(ids):
        raise AlgorithmError(f"robot {agent.robot_id}: peers {sorted(wanted - set(ids))} are not robots of the "
                             f"team {ids}")
    return ids, [r for r in ids if r in wanted and r != agent.robot_id], {r: k for k, r in enumerate(ids)}


class StepEngine:
    """Runs one robot's :class:`RobotAgent` over a link, one step per :meth:`step`.

    Args:
        agent: the robot (its ``index`` is its position in ``robot_ids``, the wire sender id).
        link: its end of the medium; the engine answers image requests through it.
        robot_ids: every robot of the team in wire-index order.
        peers: the robots it exchanges with and makes pair records for (default: all others).
        wait_s: deadline of each wait (descriptors, replies, poses).
    """

    def __init__(self, agent: RobotAgent, link: Link, robot_ids: Sequence[str],
                 peers: Iterable[str] | None = None, wait_s: float = 0.0) -> None:
        self.agent, self.link, self.wait_s = agent, link, float(wait_s)
        self.robot_ids, self.peers, self.index_of = team_roster(agent, robot_ids, peers)
        link.serve(self._answer)

    def _answer(self, peer: str, request: ImageRequest) -> bytes | None:
        """Image request -> reply frame (counted as this robot's ``reply`` bytes)."""
        if self.agent.cur is None:
            return None
        reply = self.agent.image_reply(request)
        if reply is None:
            return None
        frame = reply.encode()
        self.agent.count_sent("reply", len(frame))
        return frame

    def _book(self, inbox: Inbox) -> Inbox:
        for what in inbox.degradations:
            self.agent.degrade(what)
        return inbox

    def step(self, image: np.ndarray, context: FrameContext, stamp_s: float | None = None) -> StepRun:
        """One step of this robot: pair records with it as ego, and its robot record."""
        a, link, t, peers = self.agent, self.link, int(context.step), self.peers
        # 1. describe; 2. broadcast the descriptor
        a.begin_step(image, context, stamp_s)
        link.begin(t)
        a.count_sent("descriptor", link.broadcast("descriptor", a.descriptor_frame(a.config.messages.descriptor_dtype)))
        yield "descriptor"
        # 3. gate: score every peer's descriptor, request the images whose score passes tau
        # (and that the request policy wants: the policy group; the paper's asks them all)
        got = self._book(link.gather(t, "descriptor", peers, self.wait_s))
        for p in got.gone:
            a.peer_gone(p)
        a.score_descriptors({p: got.message(p) for p in peers})  # coded messages are decoded by the agent
        asked = {p: ImageRequest(a.index, t, self.index_of[p]).encode() for p in peers if a.wants_image(p)}
        replies = self._book(link.request(t, asked, self.wait_s))
        for _ in range(int(a.config.messages.request_retries)):  # a lost request or reply: ask once more
            again = {p: f for p, f in asked.items() if p not in replies.messages}
            if not again:
                break
            more = self._book(link.request(t, again, self.wait_s))
            for p in again:
                a.degrade("msg:request-retried")
            replies.messages.update(more.messages)
            for p, n in more.sent.items():
                replies.sent[p] = replies.sent.get(p, 0) + n
        for n in replies.sent.values():
            a.count_sent("request", n)
        for p in asked:
            if p in replies.messages:
                a.accept_reply(p, replies.messages[p].message)
            else:
                a.reply_missing(p)
        # 4. ONE joint pass; 5. scale; 6. odometry; 7. broadcast the pose (and, shared, the direct estimates)
        a.joint_pass()
        a.estimate_scale()
        a.update_odometry()
        a.count_sent("pose", link.broadcast("pose", a.pose_frame()))
        share = bool(a.config.messages.share_estimates)  # our extension: the direct estimates of this step too
        if share:
            a.count_sent("estimate", link.broadcast("estimate", a.estimate_frame(self.index_of)))
        yield "pose"
        a.note_pose(a.robot_id, t, a.X)
        for p, got_pose in self._book(link.gather(t, "pose", peers, self.wait_s)).messages.items():
            a.note_pose(p, got_pose.message.step, got_pose.message.T_odom_cam)
        if share:
            for p, got_est in self._book(link.gather(t, "estimate", peers, self.wait_s)).messages.items():
                a.note_estimates(p, got_est.message)
        # 8. relative pose per peer: direct when the gate opened and the pass placed the other's view
        # (verified against the anchor), else the anchor propagated
        pairs = []
        for p in peers:
            nbytes = replies.sent.get(p, 0) + (replies.messages[p].nbytes if p in replies.messages else 0)
            pairs.append(a.pair_record(p, nbytes))
        # 9. memory management
        a.manage_memory()
        return StepResult(step=t, pairs=pairs, robots=[a.record()])


def drive(runs: Sequence[StepRun]) -> list[StepResult]:
    """Advance every run to its next wait point, in order, until all have returned."""
    out: list[StepResult | None] = [None] * len(runs)
    live = list(range(len(runs)))
    while live:
        still = []
        for k in live:
            try:
                next(runs[k])
                still.append(k)
            except StopIteration as stop:
                out[k] = stop.value
        live = still
    return out  # type: ignore[return-value]
