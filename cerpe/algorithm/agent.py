"""One robot: the phases of a step of Algorithm 1 over the robot's state.

:class:`RobotAgent` knows nothing of how frames travel; :class:`~cerpe.algorithm.engine.StepEngine`
calls its methods in the order of Algorithm 1 and moves the frames over a link. Everything the robot
remembers is one :class:`~cerpe.algorithm.state.RobotState`; phases 2-3 (descriptor on the wire, gate,
request policy) are its :class:`~cerpe.algorithm.gating.Gate`, phases 7b-8 (peers' poses, shared
estimates, relative poses) its :class:`~cerpe.algorithm.relative.Relative`, the others methods here.
"""
from __future__ import annotations

import dataclasses
from typing import Mapping

import numpy as np

from ..compress import make_codec
from ..geometry import se3_inverse
from ..memory import Keyframe, KeyframeMemory
from ..messages import DescriptorMessage, EstimateMessage, ImageReply, ImageRequest, PoseMessage
from ..protocols import (
    BLANK_STD,
    BackboneOutput,
    DescriptorEncoder,
    FrameContext,
    MetricDepthSource,
    PoseBackbone,
    View,
)
from ..records import PairRecord, RobotRecord
from ..scale import recover_scale
from .config import AlgorithmConfig, AlgorithmError
from .frames import check_frame, describe, intrinsics_tuple, received_view
from .gating import Gate
from .late import LateRegistrations, checked_output
from .policy import try_hard
from .poses import check_pose, ego_motion
from .registrar import Registrar
from .relative import Relative
from .state import Previous, RobotState, StepState, timed


class RobotAgent:
    """One robot: its state (memory, odometry ``X`` from identity at its first step, anchors per peer)
    and the phases of a step.

    Phases, in order: :meth:`begin_step`, :meth:`descriptor_frame`,
    :meth:`score_descriptor`, :meth:`image_reply` / :meth:`accept_reply`,
    :meth:`joint_pass`, :meth:`estimate_scale`, :meth:`update_odometry`,
    :meth:`pose_frame`, :meth:`note_pose`, :meth:`pair_record`, :meth:`manage_memory`,
    :meth:`record`. A new agent starts from nothing.
    """

    def __init__(self, robot_id: str, index: int, config: AlgorithmConfig, descriptor: DescriptorEncoder,
                 backbone: PoseBackbone, depth: MetricDepthSource, registrar: Registrar | None = None) -> None:
        self.robot_id = str(robot_id)
        self.index = int(index)
        self.config = config.resolved(getattr(descriptor, "thresholds", None))  # idempotent on concrete values
        self.descriptor = descriptor
        self.backbone = backbone
        self.depth = depth
        self.s = RobotState(self.robot_id, self.index, KeyframeMemory(self.config.memory))
        self.step_rule = self.config.odometry.step_rule()
        # compressed descriptor messages (cerpe.compress; None: the full descriptor at descriptor_dtype)
        msgs = self.config.messages
        codec = make_codec(msgs.descriptor_codec, msgs.projection)
        tau = float(self.config.gate.tau)
        if codec is not None:
            dim = getattr(descriptor, "dim", None)
            if dim is not None and int(dim) != codec.projection.dim:
                raise AlgorithmError(f"robot {self.robot_id}: descriptor_codec {codec.name!r}: the projection "
                                     f"takes {codec.projection.dim} values, the descriptor gives {dim}")
            tau = float(msgs.codec_tau if msgs.codec_tau is not None else codec.tau if codec.tau is not None
                        else self.config.gate.tau)
        self.gate = Gate(self.s, self.config, codec, tau)
        # registrar: received images are registered apart and land when ready (None: in the joint pass)
        self.late = None if registrar is None else LateRegistrations(self.s, registrar, self.config)
        self.relative = Relative(self.s, self.config, depth, self.gate, self.late)

    # ---------------------------------------------------------------- what others read
    @property
    def X(self) -> np.ndarray:
        """``[4,4]`` this robot's odometry pose ``T_odom_cam``."""
        return self.s.X

    @property
    def cur(self) -> StepState | None:
        """This step's state (None before the first step)."""
        return self.s.cur

    @property
    def memory(self) -> KeyframeMemory:
        return self.s.memory

    def degrade(self, what: str) -> None:
        """Count a run-time fault in this step's record (names in :data:`cerpe.reasons.DEGRADATIONS`)."""
        self.s.degrade(what)

    def count_sent(self, kind: str, nbytes: int) -> None:
        """Book ``nbytes`` put on the wire this step under message ``kind``."""
        self.s.step_state().bytes_sent[kind] += int(nbytes)

    # ---------------------------------------------------------------- phases of the collaborators
    def descriptor_frame(self, dtype: str) -> bytes:
        """Phase 2: this step's descriptor as a wire frame (:meth:`Gate.descriptor_frame`)."""
        return self.gate.descriptor_frame(dtype)

    def score_descriptor(self, other: str, descriptor: np.ndarray | DescriptorMessage | None) -> float:
        """Phase 3: the gate score against a received descriptor (:meth:`Gate.score_descriptor`)."""
        return self.gate.score_descriptor(other, descriptor)

    def score_descriptors(self, received: Mapping[str, np.ndarray | DescriptorMessage | None]) -> dict[str, float]:
        """Phase 3 for every peer at once, in one matrix product (:meth:`Gate.score_descriptors`)."""
        return self.gate.score_descriptors(received)

    def peer_gone(self, other: str) -> None:
        self.gate.peer_gone(other)

    def gate_open(self, other: str) -> bool:
        return self.gate.gate_open(other)

    def wants_image(self, other: str) -> bool:
        """Phase 3: whether to request ``other``'s image (the gate and the request policy)."""
        return self.gate.wants_image(other)

    def note_pose(self, other: str, step: int, X_j: np.ndarray) -> None:
        """Phase 7: a robot's broadcast pose (:meth:`Relative.note_pose`)."""
        self.relative.note_pose(other, step, X_j)

    def reply_missing(self, other: str) -> None:
        self.relative.reply_missing(other)

    def estimate_frame(self, index_of: Mapping[str, int]) -> bytes:
        """Phase 7b: the shared estimates of this step (:meth:`Relative.estimate_frame`)."""
        return self.relative.estimate_frame(index_of)

    def note_estimates(self, other: str, msg: EstimateMessage) -> None:
        self.relative.note_estimates(other, msg)

    def pair_record(self, other: str, bytes_pair: int = 0) -> PairRecord:
        """Phase 8: this step's record about ``other`` (:meth:`Relative.pair_record`); with a registrar,
        the registrations that landed since the last step are read first."""
        if self.late is not None:
            self.late.collect(self.s.step_state())
        return self.relative.pair_record(other, bytes_pair)

    # ---------------------------------------------------------------- online by stamps (cerpe.algorithm.stamp_engine)
    def peer_absent(self, other: str) -> None:
        """``other`` is not up (not joined yet, or left): no descriptor to score, nothing counted per frame."""
        self.gate.peer_absent(other)

    def forget_peer(self, other: str) -> None:
        """``other`` came back in a new session: its odometry restarted, so what this robot knew of the
        pair (anchors, poses, graph, descriptors, requests) no longer holds."""
        for kept in (self.s.pairs, self.s.graphs, self.s.poses, self.s.pose_logs, self.s.odometers,
                     self.s.shared_anchors, self.s.shared_steps, self.s.asks, self.s.sigmas, self.s.last_descriptors):
            kept.pop(other, None)

    def pose_unknown(self, other: str) -> None:
        """No pose of ``other`` at this frame (none near its stamp): nothing is propagated with an old one."""
        self.s.poses.pop(other, None)

    def set_collab_motion(self, other: str, T_cj_now_cj_view: np.ndarray | None) -> None:
        """The motion of ``other``'s camera from the capture of its received view to this frame's (None:
        unknown; the view then gives no direct estimate)."""
        M = None if T_cj_now_cj_view is None else check_pose(T_cj_now_cj_view, f"{self.s.where()}: motion of {other}")
        self.s.step_state().collab_motion[other] = M

    # ---------------------------------------------------------------- 1. describe
    def begin_step(self, image: np.ndarray, context: FrameContext, stamp_s: float | None = None) -> np.ndarray:
        """Check the frame and describe it; returns the ``[D] float32`` descriptor it broadcasts.

        A blank frame (see :func:`cerpe.algorithm.frames.describe`) broadcasts the
        all-zero descriptor (receivers keep their gate closed), skips the joint
        pass, keeps ``X`` and is never kept as keyframe or tracking reference;
        counted once as ``frame:blank``.
        """
        step = int(context.step)
        where = self.s.where(step)
        if context.robot_id != self.robot_id:
            raise AlgorithmError(f"{where}: frame context belongs to robot {context.robot_id!r}")
        if self.s.last_step is not None and step <= self.s.last_step:
            raise AlgorithmError(f"{where}: steps must increase (previous {self.s.last_step})")
        img = check_frame(image, context, where)
        view = View(key=(self.robot_id, step), image=img, intrinsics=context.intrinsics)
        d, blank, timings, cpu = describe(self.descriptor, view, where, BLANK_STD)
        self.s.cur = StepState(step=step, stamp_s=float(step if stamp_s is None else stamp_s), image=img,
                              context=context, view=view, descriptor=np.zeros_like(d) if blank else d,
                              blank=bool(blank), timings=timings, cpu=cpu)
        if blank == "zero-norm":
            self.s.degrade("descriptor:zero-norm")
        if blank:
            self.s.degrade("frame:blank")
        return self.s.cur.descriptor

    # ---------------------------------------------------------------- 3b. image exchange
    def image_reply(self, request: ImageRequest) -> ImageReply | None:
        """Answer an image request of this step with the current image as JPEG (None: stale, counted)."""
        st = self.s.step_state()
        if request.step != st.step or request.target != self.index:
            self.s.degrade("msg:stale-request")
            return None
        if st.reply_cache is None:
            with timed(st, "gate"):
                st.reply_cache = ImageReply.from_image(self.index, st.step, st.image,
                                                       intrinsics_tuple(st.context.intrinsics),
                                                       quality=self.config.messages.reply_quality,
                                                       codec=self.config.messages.reply_codec,
                                                       scale=self.config.messages.reply_scale)
        # the newest own pose goes with the image: this step's once odometry ran (or at the first
        # step, identity), else the previous step's; a requester whose pose message is lost bridges from it
        now = bool(st.ego_status) or self.s.last_step is None
        return dataclasses.replace(st.reply_cache, pose_step=st.step if now else self.s.last_step,
                                   T_odom_cam=self.s.X.copy())

    def accept_reply(self, other: str, reply: ImageReply, same_step: bool = True) -> View | None:
        """Decode a collaborator's JPEG for the joint pass (see :func:`~cerpe.algorithm.frames.received_view`).

        ``same_step`` False (online by stamps): the reply is of the peer's own frame ``reply.step``,
        not of this step; the caller files the pose it carries and sets the peer's motion since
        (:meth:`set_collab_motion`)."""
        st = self.s.step_state()
        if same_step and reply.step != st.step:
            self.s.degrade("msg:stale-reply")
            return None
        with timed(st, "gate"):
            view, fault = received_view(other, reply)
        if same_step and reply.T_odom_cam is not None and 0 <= reply.pose_step <= st.step:
            self.relative.log_pose(other, reply.pose_step, reply.T_odom_cam)
        if view is None:  # the pair gets no direct estimate this step
            self.s.degrade(f"msg:{fault}")
            st.gate_reason[other] = f"reply-{fault}"
            return None
        # the costliest registration only for a gated image (policy.mode "always" asks without the gate)
        hard = self.gate.gate_open(other) and try_hard(self.gate.pair_view(other, st.step))
        view = dataclasses.replace(view, try_hard=hard)
        st.collab_views[other] = view
        return view

    # ---------------------------------------------------------------- 4. joint pass
    def joint_pass(self) -> BackboneOutput | None:
        """ONE backbone pass over ``[current] + keyframes (newest first) (+ previous frame) + collaborators``.

        Kept views come with the memo the backbone gave them as current view, every view
        with its role (``View.role``). In a pass without collaborators the own views besides the
        current one go with ``pose_wanted`` False (:class:`~cerpe.protocols.View`): ego-motion reads
        the reference alone, so a backbone may skip placing the others. None for a blank frame (no pass).
        """
        st = self.s.step_state()
        st.passed = True
        if st.blank:
            return None
        kfs = self.s.memory.newest_first()
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
        prev = self.s.previous
        st.prev_index = None
        if self.config.odometry.track_previous and prev is not None and kfs and prev.view.key != kfs[0].key:
            st.prev_index = len(views)
            st.own_views[st.prev_index] = (prev.step, prev.T_odom_cam)
            views.append(dataclasses.replace(prev.view, role="previous"))
        n_own = len(views)
        collab_index: dict[str, int] = {}
        for other, v in st.collab_views.items():
            collab_index[other] = len(views)
            views.append(dataclasses.replace(v, role="collaborator"))
        if self.late is not None and collab_index:  # the joint pass to the registrar; own views here
            self.late.submit(st, views, collab_index)
            views = views[:n_own]
        else:
            st.collab_index.update(collab_index)
        if len(views) == n_own and self.config.scale.metric_unit:
            # no collaborator to place through them: ego-motion reads the reference view alone
            views = [views[0]] + [dataclasses.replace(v, pose_wanted=False) for v in views[1:]]
        with timed(st, "backbone"):
            out = self.backbone.infer(views)
        st.out = out = checked_output(out, len(views), self.s.where(), self.s.degrade)
        for part, seconds in (out.timings_s or {}).items():  # the backbone's own profile of its pass (cerpe bench)
            if isinstance(seconds, (int, float)) and np.isfinite(seconds):
                st.parts[f"backbone:{part}"] += float(seconds)
        st.view = dataclasses.replace(st.view, memo=out.memos[0])  # travels with the frame if it is kept
        return out

    # ---------------------------------------------------------------- 5. scale
    def _current_depth(self) -> np.ndarray | None:
        st = self.s.step_state()
        done, d = st.depth_cache
        if done:
            return d
        # a sensor's depth comes with the frame: its reading (or simulation) is timed apart (MetricDepthSource)
        with timed(st, "scale", "sensor" if getattr(self.depth, "sensor", False) is True else ""):
            d = self.depth.depth_m(st.view, st.context)
        if d is not None:
            d = np.asarray(d, dtype=np.float32)
            if d.ndim != 2 or d.size == 0:
                raise AlgorithmError(f"{self.s.where()}: depth source {getattr(self.depth, 'name', '?')!r} "
                                     f"returned shape {d.shape}, expected [H,W]")
        else:
            self.s.degrade("depth:none")
        st.depth_cache = (True, d)
        return d

    def _pass(self, what: str) -> StepState:
        st = self.s.step_state()
        if not st.passed:
            raise AlgorithmError(f"{self.s.where()}: {what} before joint_pass")
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
        kfs = self.s.memory.newest_first()
        metric, idx = ([kf.depth_ref_m for kf in kfs], list(range(1, 1 + len(kfs)))) if kfs \
            else ([self._current_depth()], [0])
        with timed(st, "scale"):
            est = recover_scale(metric, [out.depth[k] if out.valid[k] else None for k in idx],
                                [out.depth_conf[k] for k in idx], min_pixels=self.config.scale.min_pixels)
        for _, reason in est.skipped:
            self.s.degrade(f"scale:skipped-{reason}")
        if est.ok:
            st.scale = self.s.last_scale = est.scale
        elif np.isfinite(self.s.last_scale):
            st.scale = self.s.last_scale
            self.s.degrade("scale:fallback-last")
        elif not getattr(self.depth, "metric", True):  # a source that never has metric depth
            st.scale, st.metric_scale = 1.0, False
            self.s.degrade("scale:unit-no-depth")
        else:
            self.s.degrade("scale:unavailable")
        return st.scale

    # ---------------------------------------------------------------- 6. odometry
    def update_odometry(self, T_odom_cam: np.ndarray | None = None) -> np.ndarray:
        """``X_t`` through the pass's reference view, else the previous frame, else the newest placed keyframe.

        Only differences within one pass are used, so a new backbone frame never
        makes ``X`` jump; without an estimate ``X`` keeps its value. ``T_odom_cam`` (online: the
        robot's own odometry at this frame, e.g. wheels) is taken as ``X`` instead (``external``).
        """
        st = self._pass("update_odometry")
        if T_odom_cam is not None:
            st.ego_status = "external"
            self.s.X = check_pose(T_odom_cam, f"{self.s.where()}: the robot's odometry")
            self.s.ego_base, self.s.ego_speeds = None, []
            return self.s.X
        out = st.out
        kfs = self.s.memory.newest_first()
        if out is None:
            st.ego_status = "blank"
            self.s.ego_base, self.s.ego_speeds = None, []  # what the next step measures from is unknown
            return self.s.X
        if not kfs:
            st.ego_status = "first" if self.s.last_step is None else "no-keyframe"
            if st.ego_status == "no-keyframe":
                self.s.degrade("ego:no-keyframe")
                self.s.ego_base, self.s.ego_speeds = None, []
            else:
                self.s.ego_base = (st.stamp_s, self.s.X.copy())
            return self.s.X
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
                starts[ref] = self.s.previous.T_odom_cam if ref == p else kfs[ref - 1].T_odom_cam
            if p is not None:
                starts.setdefault(p, self.s.previous.T_odom_cam)
            for k, kf in enumerate(kfs):
                starts.setdefault(1 + k, kf.T_odom_cam)
            for s, X_s in starts.items():
                if out.valid[s]:
                    st.ego_status = "ok"
                    self.s.X = self._step_rule(st, ego_motion(X_s, out.T_frame_cam[s], out.T_frame_cam[0], st.scale))
                    if s != ref and s != p and s > 1:
                        self.s.degrade("ego:older-keyframe")
                    return self.s.X
            st.ego_status = "keyframes-invalid"
        self.s.degrade("ego:no-estimate")
        self.s.ego_base, self.s.ego_speeds = None, []
        return self.s.X

    def _step_rule(self, st: StepState, X_new: np.ndarray) -> np.ndarray:
        """``X_new``, or a held pose when its step is implausibly slow after the accepted ones
        (:class:`~cerpe.scale.StepLengthRule`).

        The held pose is the last pose moved by the pass's rotation and by the last accepted
        step's translation direction at the reference speed (``ego_status`` ``held``, counted
        ``ego:step-held``; the pose graph counts the step as lost odometry).

        After a step without an estimate (``X`` kept) the history starts again: what the next
        step is measured from no longer is where the robot was."""
        base, hist = self.s.ego_base, self.s.ego_speeds
        self.s.ego_base = (st.stamp_s, X_new)
        if base is None or not st.stamp_s > base[0]:
            self.s.ego_speeds = []
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
            self.s.ego_base = (st.stamp_s, X)
            st.ego_status = "held"
            self.s.degrade("ego:step-held")
            return X
        self.s.ego_speeds = (hist + [(length / dt, st.stamp_s, inc[:3, 3].copy())])[-int(self.step_rule.window):]
        return X_new

    # ---------------------------------------------------------------- 7. pose broadcast
    def pose_frame(self) -> bytes:
        st = self.s.step_state()
        return PoseMessage(self.index, st.step, self.s.X).encode()

    # ---------------------------------------------------------------- 9. memory
    def manage_memory(self) -> bool:
        """Keyframe rule and tracking reference; returns whether the current frame became a keyframe."""
        st = self.s.step_state()
        st.keyframe = self._keyframe_rule(st)
        self._keep_previous(st)
        return st.keyframe

    def _keyframe_rule(self, st: StepState) -> bool:
        out = st.out
        if st.blank:
            return False  # a blank frame (counted) is never worth keeping
        if len(self.s.memory) and (out is None or not out.valid[0]):
            return False  # a view the backbone cannot place would only break later passes
        if st.ego_status == "keyframes-invalid":
            self.s.memory.clear()
            self.s.degrade("memory:reinit")
            insert = True
        else:
            insert, _, _, _ = self.s.memory.decide(st.descriptor, st.step)
        if insert:
            self.s.memory.insert(Keyframe(step=st.step, key=st.view.key, descriptor=st.descriptor,
                                        image=st.image, intrinsics=st.context.intrinsics,
                                        T_odom_cam=self.s.X.copy(), depth_ref_m=self._current_depth(),
                                        memo=st.view.memo))
        return bool(insert)

    def _keep_previous(self, st: StepState) -> None:
        """This frame becomes next step's tracking reference when its pose is an estimate.

        A blank frame leaves the reference as it was (the last good frame), so the
        next good frame chains through that one.
        """
        if st.blank:
            return
        self.s.previous = None
        if not self.config.odometry.track_previous:
            return
        if st.ego_status in ("ok", "held", "external") or (st.ego_status == "first" and st.out is not None):
            # joint_pass attached this frame's depth and memo to st.view
            self.s.previous = Previous(step=st.step, view=st.view, T_odom_cam=self.s.X.copy())

    def record(self) -> RobotRecord:
        st = self.s.step_state()
        self.s.last_step = st.step
        if self.late is not None:
            self.late.step_done(st)
        return RobotRecord(step=st.step, stamp_s=st.stamp_s, robot=self.robot_id, T_odom_cam=self.s.X.copy(),
                           scale=float(st.scale), n_keyframes=len(self.s.memory), keyframe=st.keyframe,
                           bytes_sent=dict(st.bytes_sent), timings_s={k: float(v) for k, v in st.timings.items()},
                           degradations=list(st.degradations), cpu_s={k: float(v) for k, v in st.cpu.items()},
                           parts_s={k: float(v) for k, v in st.parts.items()})
