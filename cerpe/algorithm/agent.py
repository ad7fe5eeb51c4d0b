"""One robot: its memory, odometry, anchors, and the per-phase methods of a step.

:class:`RobotAgent` knows nothing of how frames travel; :class:`~cerpe.algorithm.engine.StepEngine`
calls its methods in the order of Algorithm 1 and moves the frames over a link.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from ..compress import make_codec
from ..geometry import se3_inverse
from ..memory import Keyframe, KeyframeMemory
from ..messages import ImageReply, ImageRequest, PoseMessage
from ..protocols import (
    BLANK_STD,
    BackboneOutput,
    DescriptorEncoder,
    FrameContext,
    MetricDepthSource,
    PoseBackbone,
    View,
)
from ..records import RobotRecord
from ..scale import recover_scale
from .anchors import Anchor, PairAnchors
from .bridge import PoseLog
from .config import AlgorithmConfig, AlgorithmError
from .frames import check_frame, describe, intrinsics_tuple, received_view
from .gating import GateSide
from .graph import PairGraph
from .policy import try_hard
from .poses import ego_motion
from .relative import PairSide
from .state import Previous, StepState

log = logging.getLogger(__name__)


class RobotAgent(GateSide, PairSide):
    """One robot: its memory, odometry ``X`` (identity at its first step), anchors per peer.

    Phases, in order: :meth:`begin_step`, :meth:`descriptor_frame`,
    :meth:`score_descriptor`, :meth:`image_reply` / :meth:`accept_reply`,
    :meth:`joint_pass`, :meth:`estimate_scale`, :meth:`update_odometry`,
    :meth:`pose_frame`, :meth:`note_pose`, :meth:`relative`, :meth:`manage_memory`,
    :meth:`record`. Everything the robot remembers between steps (keyframes with
    their backbone memos, the previous frame, scale, anchors, peers' poses) lives
    here, so a new agent starts from nothing.
    """

    def __init__(self, robot_id: str, index: int, config: AlgorithmConfig, descriptor: DescriptorEncoder,
                 backbone: PoseBackbone, depth: MetricDepthSource) -> None:
        self.robot_id = str(robot_id)
        self.index = int(index)
        self.config = config.resolved(getattr(descriptor, "thresholds", None))  # idempotent on concrete values
        self.descriptor = descriptor
        self.backbone = backbone
        self.depth = depth
        self.memory = KeyframeMemory(self.config.memory)
        self.X = np.eye(4)
        self.last_scale = float("nan")
        self.step_rule = self.config.odometry.step_rule()
        self.ego_base: tuple[float, np.ndarray] | None = None  # (stamp, X) of the last pose the odometry set
        self.ego_speeds: list[tuple[float, float, np.ndarray]] = []  # accepted steps: (speed, stamp, t), newest last
        self.pairs: dict[str, PairAnchors] = {}
        self.shared_anchors: dict[str, list[Anchor]] = {}  # peer -> the recent candidates shared estimates made
        self.shared_steps: dict[str, int] = {}  # peer -> step of its last usable shared estimate (request policy)
        self.graphs: dict[str, PairGraph] = {}  # backend="graph": one pose graph per peer
        self.sigmas: dict[str, tuple[float, float]] = {}  # backend="graph": last (rot rad, pos m) sigma per peer
        self.asks = {}  # request policy: peer -> what its requests brought (policy.AskLog; GateSide.note_request)
        self.poses: dict[str, tuple[int, np.ndarray]] = {}
        self.last_descriptors: dict[str, tuple[int, np.ndarray]] = {}  # peer -> (step, values) last scored fresh
        self.pose_logs: dict[str, PoseLog] = {}  # peer -> poses seen (messages, replies): bridges a lost one
        self.odometers: dict[str, tuple[int, np.ndarray, float]] = {}  # robot -> (step, position, metres)
        self.last_step: int | None = None
        self.cur: StepState | None = None
        self.previous: Previous | None = None
        # compressed descriptor messages (cerpe.compress; None: the full descriptor at descriptor_dtype)
        msgs = self.config.messages
        self.codec = make_codec(msgs.descriptor_codec, msgs.projection)
        self.gate_tau = float(self.config.gate.tau)
        if self.codec is not None:
            dim = getattr(descriptor, "dim", None)
            if dim is not None and int(dim) != self.codec.projection.dim:
                raise AlgorithmError(f"robot {self.robot_id}: descriptor_codec {self.codec.name!r}: the projection "
                                     f"takes {self.codec.projection.dim} values, the descriptor gives {dim}")
            tau = msgs.codec_tau
            self.gate_tau = float(tau if tau is not None else self.codec.tau if self.codec.tau is not None
                                  else self.config.gate.tau)
        self._kf_wire: dict[int, np.ndarray] = {}  # keyframe step -> its codec values (the memory-aware gate)

    # ---------------------------------------------------------------- helpers
    def _where(self, step: int | None = None) -> str:
        s = self.cur.step if step is None and self.cur is not None else step
        return f"robot {self.robot_id} step {s}"

    def _state(self) -> StepState:
        if self.cur is None:
            raise AlgorithmError(f"robot {self.robot_id}: no step in progress (call begin_step first)")
        return self.cur

    def degrade(self, what: str) -> None:
        """Count a run-time fault in this step's record (names in :data:`cerpe.algorithm.DEGRADATIONS`)."""
        self._state().degradations.append(what)
        log.debug("%s: %s", self._where(), what)

    def count_sent(self, kind: str, nbytes: int) -> None:
        """Book ``nbytes`` put on the wire this step under message ``kind``."""
        self._state().bytes_sent[kind] += int(nbytes)

    # ---------------------------------------------------------------- 1. describe
    def begin_step(self, image: np.ndarray, context: FrameContext, stamp_s: float | None = None) -> np.ndarray:
        """Check the frame and describe it; returns the ``[D] float32`` descriptor it broadcasts.

        A blank frame (see :func:`cerpe.algorithm.frames.describe`) broadcasts the
        all-zero descriptor (receivers keep their gate closed), skips the joint
        pass, keeps ``X`` and is never kept as keyframe or tracking reference;
        counted once as ``frame:blank``.
        """
        step = int(context.step)
        where = self._where(step)
        if context.robot_id != self.robot_id:
            raise AlgorithmError(f"{where}: frame context belongs to robot {context.robot_id!r}")
        if self.last_step is not None and step <= self.last_step:
            raise AlgorithmError(f"{where}: steps must increase (previous {self.last_step})")
        img = check_frame(image, context, where)
        view = View(key=(self.robot_id, step), image=img, intrinsics=context.intrinsics)
        d, blank, timings = describe(self.descriptor, view, where, BLANK_STD)
        self.cur = StepState(step=step, stamp_s=float(step if stamp_s is None else stamp_s), image=img,
                              context=context, view=view, descriptor=np.zeros_like(d) if blank else d,
                              blank=bool(blank), timings=timings)
        if blank == "zero-norm":
            self.degrade("descriptor:zero-norm")
        if blank:
            self.degrade("frame:blank")
        return self.cur.descriptor

    # ---------------------------------------------------------------- 3b. image exchange
    def image_reply(self, request: ImageRequest) -> ImageReply | None:
        """Answer an image request of this step with the current image as JPEG (None: stale, counted)."""
        st = self._state()
        if request.step != st.step or request.target != self.index:
            self.degrade("msg:stale-request")
            return None
        if st.reply_cache is None:
            t0 = time.perf_counter()
            st.reply_cache = ImageReply.from_image(self.index, st.step, st.image,
                                                   intrinsics_tuple(st.context.intrinsics),
                                                   quality=self.config.messages.reply_quality,
                                                   codec=self.config.messages.reply_codec,
                                                   scale=self.config.messages.reply_scale)
            st.timings["gate"] += time.perf_counter() - t0
        # the newest own pose goes with the image: this step's once odometry ran (or at the first
        # step, identity), else the previous step's; a requester whose pose message is lost bridges from it
        now = bool(st.ego_status) or self.last_step is None
        return dataclasses.replace(st.reply_cache, pose_step=st.step if now else self.last_step,
                                   T_odom_cam=self.X.copy())

    def accept_reply(self, other: str, reply: ImageReply) -> View | None:
        """Decode a collaborator's JPEG for the joint pass (see :func:`~cerpe.algorithm.frames.received_view`)."""
        st = self._state()
        if reply.step != st.step:
            self.degrade("msg:stale-reply")
            return None
        t0 = time.perf_counter()
        view, fault = received_view(other, reply)
        st.timings["gate"] += time.perf_counter() - t0
        if reply.T_odom_cam is not None and 0 <= reply.pose_step <= st.step:
            self._log_pose(other, reply.pose_step, reply.T_odom_cam)
        if view is None:  # the pair gets no direct estimate this step
            self.degrade(f"msg:{fault}")
            st.gate_reason[other] = f"reply-{fault}"
            return None
        # the costliest registration only for a gated image (request_policy "always" asks without the gate)
        hard = self.gate_open(other) and try_hard(self._pair_view(other, st.step))
        view = dataclasses.replace(view, try_hard=hard)
        st.collab_views[other] = view
        return view

    # ---------------------------------------------------------------- 4. joint pass
    def joint_pass(self) -> BackboneOutput | None:
        """ONE backbone pass over ``[current] + keyframes (newest first) (+ previous frame) + collaborators``.

        Kept views come with the memo the backbone gave them as current view, every view
        with its role (``View.role``). None for a blank frame (no pass).
        """
        st = self._state()
        st.passed = True
        if st.blank:
            return None
        kfs = self.memory.newest_first()
        # metric depth priors: each keyframe's reference, and the current frame's when it is
        # computed anyway (no keyframe yet: the scale needs it; track_previous: the next step does)
        rel = getattr(self.depth, "rel_sigma", None)  # the depth source's own word on its scale noise
        rel = None if rel is None else float(rel)
        if not kfs or self.config.odometry.track_previous:
            st.view = dataclasses.replace(st.view, depth_m=self._current_depth(), depth_rel_sigma=rel)
        st.view = dataclasses.replace(st.view, role="current")
        views = [st.view] + [View(kf.key, kf.image, kf.intrinsics, kf.depth_ref_m, kf.memo, role="keyframe",
                                  depth_rel_sigma=rel) for kf in kfs]
        st.own_views = {0: (st.step, None)}
        st.own_views.update({1 + k: (kf.step, kf.T_odom_cam) for k, kf in enumerate(kfs)})
        prev = self.previous
        st.prev_index = None
        if self.config.odometry.track_previous and prev is not None and kfs and prev.view.key != kfs[0].key:
            st.prev_index = len(views)
            st.own_views[st.prev_index] = (prev.step, prev.T_odom_cam)
            views.append(dataclasses.replace(prev.view, role="previous"))
        for other, v in st.collab_views.items():
            st.collab_index[other] = len(views)
            views.append(dataclasses.replace(v, role="collaborator"))
        t0 = time.perf_counter()
        out = self.backbone.infer(views)
        st.timings["backbone"] += time.perf_counter() - t0
        if not isinstance(out, BackboneOutput) or len(out.valid) != len(views):
            n = len(out.valid) if isinstance(out, BackboneOutput) else type(out).__name__
            raise AlgorithmError(f"{self._where()}: backbone returned {n} views for {len(views)} given")
        valid = np.asarray(out.valid, dtype=bool).copy()
        for k in range(len(views)):
            if valid[k] and not np.all(np.isfinite(out.T_frame_cam[k])):
                valid[k] = False
                out.reasons[k] = "non-finite pose"
                self.degrade("backbone:non-finite-pose")
        out.valid = valid
        st.out = out
        st.view = dataclasses.replace(st.view, memo=out.memos[0])  # travels with the frame if it is kept
        return out

    # ---------------------------------------------------------------- 5. scale
    def _current_depth(self) -> np.ndarray | None:
        st = self._state()
        done, d = st.depth_cache
        if done:
            return d
        t0 = time.perf_counter()
        d = self.depth.depth_m(st.view, st.context)
        st.timings["scale"] += time.perf_counter() - t0
        if d is not None:
            d = np.asarray(d, dtype=np.float32)
            if d.ndim != 2 or d.size == 0:
                raise AlgorithmError(f"{self._where()}: depth source {getattr(self.depth, 'name', '?')!r} "
                                     f"returned shape {d.shape}, expected [H,W]")
        else:
            self.degrade("depth:none")
        st.depth_cache = (True, d)
        return d

    def _pass(self, what: str) -> StepState:
        st = self._state()
        if not st.passed:
            raise AlgorithmError(f"{self._where()}: {what} before joint_pass")
        return st

    def estimate_scale(self) -> float:
        """Memory scale of this pass (NaN when none, not even a previous one, and for a blank frame)."""
        st = self._pass("estimate_scale")
        out = st.out
        if out is None:
            return st.scale
        if out.metric_unit and self.config.scale.metric_unit:
            st.scale = 1.0  # not kept as last_scale: that is the fallback of later up-to-scale passes
            return st.scale
        kfs = self.memory.newest_first()
        metric, idx = ([kf.depth_ref_m for kf in kfs], list(range(1, 1 + len(kfs)))) if kfs \
            else ([self._current_depth()], [0])
        t0 = time.perf_counter()
        est = recover_scale(metric, [out.depth[k] if out.valid[k] else None for k in idx],
                            [out.depth_conf[k] for k in idx], min_pixels=self.config.scale.min_pixels)
        st.timings["scale"] += time.perf_counter() - t0
        for _, reason in est.skipped:
            self.degrade(f"scale:skipped-{reason}")
        if est.ok:
            st.scale = self.last_scale = est.scale
        elif np.isfinite(self.last_scale):
            st.scale = self.last_scale
            self.degrade("scale:fallback-last")
        elif not getattr(self.depth, "metric", True):  # a source that never has metric depth
            st.scale, st.metric_scale = 1.0, False
            self.degrade("scale:unit-no-depth")
        else:
            self.degrade("scale:unavailable")
        return st.scale

    # ---------------------------------------------------------------- 6. odometry
    def update_odometry(self) -> np.ndarray:
        """``X_t`` through the pass's reference view, else the previous frame, else the newest placed keyframe.

        Only differences within one pass are used, so a new backbone frame never
        makes ``X`` jump; without an estimate ``X`` keeps its value.
        """
        st = self._pass("update_odometry")
        out = st.out
        kfs = self.memory.newest_first()
        if out is None:
            st.ego_status = "blank"
            self.ego_base, self.ego_speeds = None, []  # what the next step measures from is unknown
            return self.X
        if not kfs:
            st.ego_status = "first" if self.last_step is None else "no-keyframe"
            if st.ego_status == "no-keyframe":
                self.degrade("ego:no-keyframe")
                self.ego_base, self.ego_speeds = None, []
            else:
                self.ego_base = (st.stamp_s, self.X.copy())
            return self.X
        if not out.valid[0]:
            st.ego_status = "current-invalid"
        elif not np.isfinite(st.scale):
            st.ego_status = "no-scale"
        else:
            # pass index -> odometry pose of that view, in the order they are tried: the view the
            # backbone measured the current one against, the previous frame, keyframes newest first
            starts: dict[int, np.ndarray] = {}
            p, ref = st.prev_index, out.reference
            if ref is not None and (ref == p or 1 <= ref <= len(kfs)):
                starts[ref] = self.previous.T_odom_cam if ref == p else kfs[ref - 1].T_odom_cam
            if p is not None:
                starts.setdefault(p, self.previous.T_odom_cam)
            for k, kf in enumerate(kfs):
                starts.setdefault(1 + k, kf.T_odom_cam)
            for s, X_s in starts.items():
                if out.valid[s]:
                    st.ego_status = "ok"
                    self.X = self._step_rule(st, ego_motion(X_s, out.T_frame_cam[s], out.T_frame_cam[0], st.scale))
                    if s != ref and s != p and s > 1:
                        self.degrade("ego:older-keyframe")
                    return self.X
            st.ego_status = "keyframes-invalid"
        self.degrade("ego:no-estimate")
        self.ego_base, self.ego_speeds = None, []
        return self.X

    def _step_rule(self, st: StepState, X_new: np.ndarray) -> np.ndarray:
        """``X_new``, or, when its step is implausibly slow after the accepted ones
        (:class:`~cerpe.scale.StepLengthRule`), the last pose moved by the pass's rotation and
        the last accepted step's translation direction at the reference speed (``ego_status``
        ``held``, counted ``ego:step-held``; the pose graph counts the step as lost odometry).

        After a step without an estimate (``X`` kept) the history starts again: what the next
        step is measured from no longer is where the robot was."""
        base, hist = self.ego_base, self.ego_speeds
        self.ego_base = (st.stamp_s, X_new)
        if base is None or not st.stamp_s > base[0]:
            self.ego_speeds = []
            return X_new
        dt = st.stamp_s - base[0]
        inc = se3_inverse(base[1]) @ X_new
        length = float(np.linalg.norm(inc[:3, 3]))
        ref = self.step_rule.reference([v for v, _, _ in hist])
        if ref is not None and not self.step_rule.plausible(length, dt, ref, st.stamp_s - hist[-1][1]):
            held = inc.copy()
            t_ref = hist[-1][2]
            n = float(np.linalg.norm(t_ref))
            held[:3, 3] = t_ref * (ref * dt / n) if n > 0 else 0.0
            X = base[1] @ held
            self.ego_base = (st.stamp_s, X)
            st.ego_status = "held"
            self.degrade("ego:step-held")
            return X
        self.ego_speeds = (hist + [(length / dt, st.stamp_s, inc[:3, 3].copy())])[-int(self.step_rule.window):]
        return X_new

    # ---------------------------------------------------------------- 7. pose broadcast
    def pose_frame(self) -> bytes:
        st = self._state()
        return PoseMessage(self.index, st.step, self.X).encode()

    # ---------------------------------------------------------------- 9. memory
    def manage_memory(self) -> bool:
        """Keyframe rule and tracking reference; returns whether the current frame became a keyframe."""
        st = self._state()
        st.keyframe = self._keyframe_rule(st)
        self._keep_previous(st)
        return st.keyframe

    def _keyframe_rule(self, st: StepState) -> bool:
        out = st.out
        if st.blank:
            return False  # a blank frame (counted) is never worth keeping
        if len(self.memory) and (out is None or not out.valid[0]):
            return False  # a view the backbone cannot place would only break later passes
        if st.ego_status == "keyframes-invalid":
            self.memory.clear()
            self.degrade("memory:reinit")
            insert = True
        else:
            insert, _, _, _ = self.memory.decide(st.descriptor, st.step)
        if insert:
            self.memory.insert(Keyframe(step=st.step, key=st.view.key, descriptor=st.descriptor,
                                        image=st.image, intrinsics=st.context.intrinsics,
                                        T_odom_cam=self.X.copy(), depth_ref_m=self._current_depth(),
                                        memo=st.view.memo))
        return bool(insert)

    def _keep_previous(self, st: StepState) -> None:
        """This frame becomes next step's tracking reference when its pose is an estimate.

        A blank frame leaves the reference as it was (the last good frame), so the
        next good frame chains through that one.
        """
        if st.blank:
            return
        self.previous = None
        if not self.config.odometry.track_previous:
            return
        if st.ego_status in ("ok", "held") or (st.ego_status == "first" and st.out is not None):
            # joint_pass attached this frame's depth and memo to st.view
            self.previous = Previous(step=st.step, view=st.view, T_odom_cam=self.X.copy())

    def record(self) -> RobotRecord:
        st = self._state()
        self.last_step = st.step
        return RobotRecord(step=st.step, stamp_s=st.stamp_s, robot=self.robot_id, T_odom_cam=self.X.copy(),
                           scale=float(st.scale), n_keyframes=len(self.memory), keyframe=st.keyframe,
                           bytes_sent=dict(st.bytes_sent), timings_s={k: float(v) for k, v in st.timings.items()},
                           degradations=list(st.degradations))
