"""What one robot holds: between steps (:class:`RobotState`, the one place of a robot's state) and during
a step (:class:`StepState`, dropped when the next begins); :class:`Previous` and :class:`PairInfo` are parts."""
from __future__ import annotations

import logging
import time
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Iterator

import numpy as np

from ..memory import KeyframeMemory
from ..messages import ImageReply
from ..protocols import BackboneOutput, FrameContext, View
from .config import AlgorithmError

log = logging.getLogger("cerpe.algorithm.agent")


@dataclass
class StepState:
    """What one robot holds during one step (dropped when the next begins)."""

    step: int
    stamp_s: float
    image: np.ndarray
    context: FrameContext
    view: View
    descriptor: np.ndarray
    blank: bool
    wire_descriptor: np.ndarray | None = None
    scores: dict[str, float] = field(default_factory=dict)
    memory_scores: dict[str, tuple[float, int]] = field(default_factory=dict)
    gate_reason: dict[str, str] = field(default_factory=dict)
    collab_views: dict[str, View] = field(default_factory=dict)
    passed: bool = False
    out: BackboneOutput | None = None
    collab_index: dict[str, int] = field(default_factory=dict)
    prev_index: int | None = None
    own_views: dict[int, tuple[int, np.ndarray | None]] = field(default_factory=dict)
    pair_info: dict[str, "PairInfo"] = field(default_factory=dict)
    requested: dict[str, bool] = field(default_factory=dict)  # peer -> image asked (request policy)
    skipped: dict[str, str] = field(default_factory=dict)  # peer -> why the policy skipped an open gate
    request_rank: dict[str, int] | None = None  # peer -> rank among those the policy asks (policy.max_requests)
    directs: dict[str, tuple[list, str]] = field(default_factory=dict)  # peer -> own direct estimates, reason
    shared: dict[str, tuple] = field(default_factory=dict)  # peer -> its estimate of this robot, as this robot's
    # online by stamps: peer -> T_cj(now)_cj(view), the peer camera's motion from its received view's capture
    # to this frame's (a direct estimate through that view is moved by it; None: unknown, none made);
    # absent: the same instant
    collab_motion: dict[str, np.ndarray | None] = field(default_factory=dict)
    scale: float = float("nan")
    metric_scale: bool = True  # False: s = 1 for want of metric depth (a depth source that never has any)
    ego_status: str = ""
    keyframe: bool = False
    timings: Counter = field(default_factory=Counter)  # wall seconds per stage
    cpu: Counter = field(default_factory=Counter)  # CPU seconds per stage and part, of the thread that ran it
    parts: Counter = field(default_factory=Counter)  # wall seconds of parts of stages (gate_score)
    degradations: list[str] = field(default_factory=list)
    bytes_sent: Counter = field(default_factory=Counter)
    reply_cache: ImageReply | None = None
    depth_cache: tuple[bool, np.ndarray | None] = (False, None)
    # registrations apart from the step (cerpe.algorithm.late): peers whose image went to the registrar this
    # step; peer -> what landed this step (Landed); whether this step collected
    pending_peers: set[str] = field(default_factory=set)
    landed: dict[str, Any] = field(default_factory=dict)
    collected: bool = False


@contextmanager
def timed(st: StepState, stage: str, part: str = "") -> Iterator[None]:
    """Add the wall (``perf_counter``) and CPU (``thread_time``: this thread's, so a worker's is not
    counted here) seconds of the block to ``st``'s ``stage`` (a :data:`cerpe.records.STAGES` name), and
    with ``part`` to that part of the stage too (``StepState.parts``, ``cpu``)."""
    w, c = time.perf_counter(), time.thread_time()
    try:
        yield
    finally:
        dw, dc = time.perf_counter() - w, time.thread_time() - c
        st.timings[stage] += dw
        st.cpu[stage] += dc
        if part:
            st.parts[part] += dw
            st.cpu[part] += dc


@dataclass
class PairInfo:
    """How this step's direct estimate for one peer came about (pair record columns).

    ``direct_via``: step of the own view it was registered through (-1: the current
    frame or the joint pass; -2: the peer's estimate, shared, ``messages.share_estimates``); ``verdict``: what anchor verification said (``""``
    without a direct estimate, ``"unchecked"`` with ``anchors.verify: false``);
    ``check_rot_rad``, ``check_trans_m``: its disagreement with what it was checked
    against (NaN when nothing was compared); ``direct_T``: the direct estimate itself
    (before verification), ``direct_inliers`` its registration's inliers (-1: unknown).
    """

    direct_via: int = -1
    verdict: str = ""
    check_rot_rad: float = float("nan")
    check_trans_m: float = float("nan")
    direct_T: np.ndarray | None = None
    direct_inliers: int = -1


@dataclass
class Previous:
    """The last placed frame, a one-slot tracking reference (not a keyframe); its view carries its memo."""

    step: int
    view: View
    T_odom_cam: np.ndarray


@dataclass
class RobotState:
    """Everything one robot remembers between steps (a new agent starts from nothing) and its step in progress.

    The agent's phases (:class:`~cerpe.algorithm.agent.RobotAgent`, its
    :class:`~cerpe.algorithm.gating.Gate` and :class:`~cerpe.algorithm.relative.Relative`) read and
    write it; nothing else does.

    Attributes:
        robot_id, index: this robot's id and wire index.
        memory: its bounded keyframe memory (keyframes carry their backbone memos).
        X: ``[4,4]`` odometry pose ``T_odom_cam`` (identity at the first step).
        last_scale: the last memory scale estimated (the fallback of later up-to-scale passes).
        ego_base, ego_speeds: the step-length rule's history: ``(stamp, X)`` of the last pose the odometry
            set, and the accepted steps ``(speed, stamp, t)``, newest last.
        previous: the last placed frame, the tracking reference.
        pairs: peer -> anchor verification state (:class:`~cerpe.algorithm.anchors.PairAnchors`).
        shared_anchors: peer -> the recent candidates the peer's shared estimates made.
        shared_steps: peer -> step of its last usable shared estimate.
        graphs, sigmas: ``backend.kind graph``: peer -> pose graph, and its last (rot rad, pos m) sigma.
        asks: peer -> what the requests to it brought (:class:`~cerpe.algorithm.policy.AskLog`).
        poses: robot -> ``(step, X)`` of its last broadcast pose.
        last_descriptors: peer -> ``(step, values)`` of its last descriptor scored fresh.
        pose_logs: peer -> poses seen (messages, replies): bridges a lost one.
        odometers: robot -> ``(step, position, metres travelled)``.
        kf_wire: keyframe step -> its codec values (the memory-aware gate with a compressed descriptor).
        pending: step -> its registration job not landed yet (:class:`~cerpe.algorithm.late.Pending`).
        registration_lateness: ``(steps, seconds)`` from submission to landing of every job that landed.
        last_step: the step of the last record (None before the first).
        cur: this step's :class:`StepState` (None between :meth:`begin` and the first step).
    """

    robot_id: str
    index: int
    memory: KeyframeMemory
    X: np.ndarray = field(default_factory=lambda: np.eye(4))
    last_scale: float = float("nan")
    ego_base: tuple[float, np.ndarray] | None = None
    ego_speeds: list[tuple[float, float, np.ndarray]] = field(default_factory=list)
    previous: Previous | None = None
    pairs: dict[str, Any] = field(default_factory=dict)
    shared_anchors: dict[str, list] = field(default_factory=dict)
    shared_steps: dict[str, int] = field(default_factory=dict)
    graphs: dict[str, Any] = field(default_factory=dict)
    sigmas: dict[str, tuple[float, float]] = field(default_factory=dict)
    asks: dict[str, Any] = field(default_factory=dict)
    poses: dict[str, tuple[int, np.ndarray]] = field(default_factory=dict)
    last_descriptors: dict[str, tuple[int, np.ndarray]] = field(default_factory=dict)
    pose_logs: dict[str, Any] = field(default_factory=dict)
    odometers: dict[str, tuple[int, np.ndarray, float]] = field(default_factory=dict)
    kf_wire: dict[int, np.ndarray] = field(default_factory=dict)
    pending: dict[int, Any] = field(default_factory=dict)
    registration_lateness: list[tuple[int, float]] = field(default_factory=list)
    last_step: int | None = None
    cur: StepState | None = None

    def where(self, step: int | None = None) -> str:
        """``robot <id> step <t>`` for messages (this step's when ``step`` is None)."""
        s = self.cur.step if step is None and self.cur is not None else step
        return f"robot {self.robot_id} step {s}"

    def step_state(self) -> StepState:
        """This step's state; :class:`AlgorithmError` when no step is in progress."""
        if self.cur is None:
            raise AlgorithmError(f"robot {self.robot_id}: no step in progress (call begin_step first)")
        return self.cur

    def degrade(self, what: str) -> None:
        """Count a run-time fault in this step's record (names in :data:`cerpe.reasons.DEGRADATIONS`)."""
        self.step_state().degradations.append(what)
        log.debug("%s: %s", self.where(), what)
