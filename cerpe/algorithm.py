"""CERPE, Algorithm 1 of the paper, for a team of robots exchanging real wire frames.

One call of :meth:`Team.step` is one synchronous round (``docs/ARCHITECTURE.md``,
"Algorithm 1 as implemented"):

1. every robot describes its image (``encode``/``descriptor`` stages);
2. broadcasts a :class:`~cerpe.messages.DescriptorMessage`;
3. scores every received descriptor (cosine of the *wire* values, so that both
   robots of a pair see the same score); ``score >= tau`` -> an
   :class:`~cerpe.messages.ImageRequest`, answered with a JPEG
   :class:`~cerpe.messages.ImageReply` (``gate`` stage);
4. runs ONE joint backbone pass over ``[current] + memory (newest first) +
   decoded collaborator images`` (``backbone``); view keys are ``(robot, step)``
   for a robot's own frames and ``(robot, step, "jpeg")`` for a received image;
5. recovers the metric scale from the memory keyframes' depth references
   (:func:`cerpe.scale.recover_scale`; the current frame only while the memory is
   empty) (``scale``);
6. composes its metric odometry pose through the view the backbone measured the
   current one against (``BackboneOutput.reference``: a keyframe or the previous
   frame), else the previous frame, else the newest keyframe the pass could place:
   ``X_t = X_kf @ S(inv(T_frame_kf) @ T_frame_cur)``. Only differences within one
   pass are used, so a new backbone frame never makes ``X`` jump;
7. broadcasts a :class:`~cerpe.messages.PoseMessage` with ``X_t``;
8. per other robot: gate open and the collaborator view placed -> direct
   ``T_cj_ci = S(inv(T_frame_cj) @ T_frame_ci)``, stored as the pair's anchor
   together with both robots' ``X``; otherwise the last anchor is propagated with
   both odometries (:func:`cerpe.geometry.propagate_relative_pose`), unless
   ``CerpeConfig.propagate`` is False (the paper's "w/o EM") (``propagation``);
9. applies the keyframe rule (:mod:`cerpe.memory`).

Failures that happen at run time are counted in ``RobotRecord.degradations`` and
the robot keeps going:

* ``ego:no-estimate`` -- the pass placed neither the current view nor any
  keyframe with it, or there is no scale: ``X`` keeps its last value
  (constant-position assumption).
* ``scale:fallback-last`` / ``scale:unavailable`` -- the memory gave no scale;
  the last valid one is used, or none exists yet.
* ``scale:skipped-<reason>`` -- a keyframe without usable metric depth.
* ``msg:lost`` / ``msg:garbled`` -- from :class:`cerpe.transport.Channel`.
* ``descriptor:zero-norm`` (own blank image: gate closed for every pair, frame
  not a keyframe), ``descriptor:wrong-length`` / ``descriptor:other-zero-norm``
  (a received descriptor that cannot be scored: gate closed for that pair).
* ``backbone:non-finite-pose`` -- a view the backbone called valid has a NaN pose
  (treated as not placed).
* ``memory:reinit`` -- no keyframe could be placed but the current view could:
  the memory restarts from the current frame at the last ``X``.
* ``pose:stale`` -- the other robot's pose message of this step is missing; its
  last received pose is used for propagation.
* ``anchor:not-stored-pose-missing`` -- a direct estimate was made but the other
  robot's pose of this step is missing, so it cannot serve as an anchor.
* ``ego:older-keyframe`` -- the newest keyframe was not placed, an older one was;
  ``ego:no-keyframe`` -- the memory is empty after the first step (blank frames).
* ``depth:none`` -- the depth source had nothing for the current frame.
* ``msg:stale-request`` / ``msg:stale-reply`` / ``msg:undecodable-jpeg`` /
  ``msg:unknown-sender`` -- frames that decode but cannot be used.

Malformed input to a public function (non-finite poses, empty memory, zero-size
images, an image whose depth or intrinsics have another size, descriptors of the
wrong length or non-finite, a backbone output with the wrong number of views)
raises :class:`AlgorithmError` naming the robot, step and field.

Stage timings: if the descriptor object exposes ``last_timings_s`` with keys
``encode`` and ``descriptor`` after ``describe`` (encoder features vs. the
aggregation head), those are used; otherwise the whole ``describe`` call is
booked as ``descriptor`` and ``encode`` stays 0. JPEG encoding/decoding of image
replies is booked under ``gate``.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np

from .errors import CerpeError
from .geometry import propagate_relative_pose, scale_translation, se3_inverse
from .memory import Keyframe, KeyframeMemory, MemoryConfig, cosine
from .messages import DESCRIPTOR_DTYPES, DescriptorMessage, ImageReply, ImageRequest, MessageError, PoseMessage, decode
from .protocols import BackboneOutput, DescriptorEncoder, FrameContext, MetricDepthSource, PoseBackbone, View
from .records import PairRecord, RobotRecord, StepResult
from .scale import recover_scale
from .scene import CameraIntrinsics, Encounter
from .transport import Channel

log = logging.getLogger(__name__)

PAPER_THRESHOLDS: dict[str, float] = {"tau": 0.2, "tau_m": 0.9, "tau_k": 0.2}


class AlgorithmError(CerpeError, ValueError):
    """Malformed input to the algorithm (names robot, step and field)."""


# --------------------------------------------------------------------------- config
@dataclass(frozen=True)
class CerpeConfig:
    """All parameters of the method.

    Thresholds (``tau`` gate, ``tau_m``/``tau_k`` keyframe rule) are cosine
    similarities and therefore specific to a descriptor. Precedence, highest
    first: a value set here explicitly (not None) > the descriptor's
    ``thresholds`` dict (its own calibration) > the paper's values
    (:data:`PAPER_THRESHOLDS`: 0.2 / 0.9 / 0.2, calibrated for SALAD).
    :meth:`resolved` applies this and returns a config with concrete numbers
    (that is what :class:`Team` uses and what a run records).

    Attributes:
        tau: gate threshold; ``score >= tau`` requests the collaborator's image.
        tau_m, tau_k, delta_k, memory_capacity: keyframe rule, see
            :class:`cerpe.memory.MemoryConfig` (``memory_capacity`` is the paper's L).
        propagate: False is the paper's "CERPE w/o EM": no propagation, only
            direct estimates.
        descriptor_dtype: wire precision (``fp16``: 8448 values = 16.9 KB, the
            paper's message size; ``fp32``, ``int8``).
        jpeg_quality: quality of image replies (OpenCV scale 0-100).
        min_scale_pixels: a keyframe needs this many valid depth pixels to vote
            in the scale.
        unit_scale_without_depth: for data with no metric depth at all (depth
            source ``none``): use s = 1 instead of giving up, so poses are the
            backbone's up-to-scale ones (counted as ``scale:unit-no-depth``); such
            runs are evaluated with ground-truth-scale translation only.
        track_previous: also hand the previous frame (with its metric depth as a
            prior) to the joint pass and build the odometry from the
            previous-to-current increment (METHOD.md 2: odometry composes metric
            increments); the newest keyframe is the fallback when the previous
            frame cannot be placed. Costs one more view per pass and a metric
            depth map per frame. False is the paper's pass, ``[current] +
            keyframes (+ collaborators)``, with ego-motion through a keyframe.
        backbone_metric_unit: when a pass says its unit is already the metre
            (:attr:`BackboneOutput.metric_unit`: the backbone anchored it on the
            views' metric depth), use s = 1 rather than estimating it again from the
            memory: the estimate would be 1 up to the keyframes' pose noise, which
            only adds error to every translation. False always runs METHOD.md step 4.
    """

    tau: float | None = None
    tau_m: float | None = None
    tau_k: float | None = None
    delta_k: int = 3
    memory_capacity: int = 5
    propagate: bool = True
    descriptor_dtype: str = "fp16"
    jpeg_quality: int = 90
    min_scale_pixels: int = 25
    unit_scale_without_depth: bool = False
    track_previous: bool = True
    backbone_metric_unit: bool = True

    def __post_init__(self) -> None:
        for name in ("tau", "tau_m", "tau_k"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and -1.0 <= v <= 1.0):
                raise AlgorithmError(f"config: {name} must be a cosine in [-1, 1], got {v}")
        if self.descriptor_dtype not in DESCRIPTOR_DTYPES:
            raise AlgorithmError(f"config: descriptor_dtype must be one of {list(DESCRIPTOR_DTYPES)}, "
                                 f"got {self.descriptor_dtype!r}")
        if not (0 <= int(self.jpeg_quality) <= 100):
            raise AlgorithmError(f"config: jpeg_quality must be in 0..100, got {self.jpeg_quality}")
        if int(self.min_scale_pixels) < 1:
            raise AlgorithmError(f"config: min_scale_pixels must be >= 1, got {self.min_scale_pixels}")

    def resolved(self, descriptor_thresholds: dict[str, float] | None = None) -> "CerpeConfig":
        """Concrete thresholds: explicit value > descriptor calibration > paper."""
        given = dict(descriptor_thresholds or {})
        vals = {}
        for name, paper in PAPER_THRESHOLDS.items():
            own = getattr(self, name)
            vals[name] = float(own if own is not None else given.get(name, paper))
        out = dataclasses.replace(self, **vals)
        out.memory_config()  # validates tau_k <= tau_m etc.
        return out

    def memory_config(self) -> MemoryConfig:
        r = self if self.tau_m is not None and self.tau_k is not None else self.resolved()
        return MemoryConfig(tau_m=r.tau_m, tau_k=r.tau_k, delta_k=self.delta_k, capacity=self.memory_capacity)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


# --------------------------------------------------------------------------- pure steps
def _pose(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise AlgorithmError(f"{name}: expected a 4x4 pose, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise AlgorithmError(f"{name}: pose contains NaN or inf")
    return T


def _scale(s: float) -> float:
    if not (np.isfinite(s) and s > 0):
        raise AlgorithmError(f"scale must be finite and > 0, got {s}")
    return float(s)


def ego_motion(X_kf: np.ndarray, T_frame_kf: np.ndarray, T_frame_cur: np.ndarray, s: float) -> np.ndarray:
    """Metric odometry pose of the current frame through a keyframe.

    ``X_cur = X_kf @ scale_translation(inv(T_frame_kf) @ T_frame_cur, s)``: the
    keyframe-to-current motion measured inside one pass (independent of that
    pass's frame), made metric by ``s``, appended to the keyframe's stored pose.
    """
    X_kf = _pose(X_kf, "X_kf")
    T_kf_cur = se3_inverse(_pose(T_frame_kf, "T_frame_kf")) @ _pose(T_frame_cur, "T_frame_cur")
    return X_kf @ scale_translation(T_kf_cur, _scale(s))


def direct_relative(T_frame_ci: np.ndarray, T_frame_cj: np.ndarray, s: float) -> np.ndarray:
    """Direct estimate ``T_cj_ci = scale_translation(inv(T_frame_cj) @ T_frame_ci, s)``."""
    T = se3_inverse(_pose(T_frame_cj, "T_frame_cj")) @ _pose(T_frame_ci, "T_frame_ci")
    return scale_translation(T, _scale(s))


def _intrinsics_tuple(K: CameraIntrinsics | None) -> tuple[float, float, float, float]:
    # (0, 0, 0, 0) on the wire means "unknown" (CameraIntrinsics never has fx = 0).
    return (0.0, 0.0, 0.0, 0.0) if K is None else (K.fx, K.fy, K.cx, K.cy)


# --------------------------------------------------------------------------- one robot
@dataclass
class Anchor:
    """Last direct estimate of one pair: ``T_cj_ci`` with both odometry poses then."""

    step: int
    T_cj_ci: np.ndarray
    X_i: np.ndarray
    X_j: np.ndarray


@dataclass
class _StepState:
    step: int
    stamp_s: float
    image: np.ndarray
    context: FrameContext
    view: View
    descriptor: np.ndarray
    descriptor_ok: bool
    wire_descriptor: np.ndarray | None = None
    scores: dict[str, float] = field(default_factory=dict)
    gate_reason: dict[str, str] = field(default_factory=dict)
    collab_views: dict[str, View] = field(default_factory=dict)
    out: BackboneOutput | None = None
    collab_index: dict[str, int] = field(default_factory=dict)
    prev_index: int | None = None
    scale: float = float("nan")
    ego_status: str = ""
    keyframe: bool = False
    timings: Counter = field(default_factory=Counter)
    degradations: list[str] = field(default_factory=list)
    bytes_sent: Counter = field(default_factory=Counter)
    reply_cache: ImageReply | None = None
    depth_cache: tuple[bool, np.ndarray | None] = (False, None)


@dataclass
class _Previous:
    """The last placed frame, a one-slot tracking reference (not a keyframe)."""

    step: int
    view: View
    T_odom_cam: np.ndarray


class RobotAgent:
    """One robot: its memory, odometry ``X`` (identity at its first step), anchors.

    The phases of a step are separate methods, called in order by :class:`Team`:
    :meth:`begin_step`, :meth:`score_descriptor`, :meth:`image_reply` /
    :meth:`accept_reply`, :meth:`joint_pass`, :meth:`estimate_scale`,
    :meth:`update_odometry`, :meth:`note_pose`, :meth:`relative`,
    :meth:`manage_memory`, :meth:`record`.
    """

    def __init__(self, robot_id: str, index: int, config: CerpeConfig, descriptor: DescriptorEncoder,
                 backbone: PoseBackbone, depth: MetricDepthSource) -> None:
        self.robot_id = str(robot_id)
        self.index = int(index)
        self.config = config.resolved(getattr(descriptor, "thresholds", None))  # idempotent on concrete values
        self.descriptor = descriptor
        self.backbone = backbone
        self.depth = depth
        self.memory = KeyframeMemory(self.config.memory_config())
        self.X = np.eye(4)
        self.last_scale = float("nan")
        self.anchors: dict[str, Anchor] = {}
        self.poses: dict[str, tuple[int, np.ndarray]] = {}
        self.last_step: int | None = None
        self.cur: _StepState | None = None
        self.previous: _Previous | None = None

    # ---------------------------------------------------------------- helpers
    def _where(self, step: int | None = None) -> str:
        s = self.cur.step if step is None and self.cur is not None else step
        return f"robot {self.robot_id} step {s}"

    def _state(self) -> _StepState:
        if self.cur is None:
            raise AlgorithmError(f"robot {self.robot_id}: no step in progress (call begin_step first)")
        return self.cur

    def _degrade(self, what: str) -> None:
        self._state().degradations.append(what)
        log.debug("%s: %s", self._where(), what)

    # ---------------------------------------------------------------- 1. observe
    def begin_step(self, image: np.ndarray, context: FrameContext, stamp_s: float | None = None) -> np.ndarray:
        """Validate the frame and compute its descriptor; returns ``[D] float32``."""
        step = int(context.step)
        where = self._where(step)
        if context.robot_id != self.robot_id:
            raise AlgorithmError(f"{where}: frame context belongs to robot {context.robot_id!r}")
        if self.last_step is not None and step <= self.last_step:
            raise AlgorithmError(f"{where}: steps must increase (previous {self.last_step})")
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
            raise AlgorithmError(f"{where}: image must be a non-empty [H,W,3] array, got shape {img.shape}")
        if img.dtype != np.uint8:
            raise AlgorithmError(f"{where}: image must be uint8 RGB, got dtype {img.dtype}")
        H, W = img.shape[:2]
        K = context.intrinsics
        if K is not None and (int(K.width), int(K.height)) != (W, H):
            raise AlgorithmError(f"{where}: intrinsics are for {K.width}x{K.height} but the image is {W}x{H}")
        if context.sensor_depth_m is not None:
            d = np.asarray(context.sensor_depth_m)
            if d.shape != (H, W):
                raise AlgorithmError(f"{where}: sensor_depth_m shape {d.shape} does not match the image {(H, W)}")
        view = View(key=(self.robot_id, step), image=img, intrinsics=K)
        t0 = time.perf_counter()
        desc = self.descriptor.describe(view)
        dt = time.perf_counter() - t0
        split = getattr(self.descriptor, "last_timings_s", None)
        timings: Counter = Counter()
        if isinstance(split, dict) and "encode" in split and "descriptor" in split:
            timings["encode"] += float(split["encode"])
            timings["descriptor"] += float(split["descriptor"])
        else:
            timings["descriptor"] += dt
        d = np.asarray(desc, dtype=np.float32)
        dim = int(getattr(self.descriptor, "dim", d.size))
        if d.ndim != 1 or d.size != dim:
            raise AlgorithmError(f"{where}: descriptor has shape {d.shape}, expected [{dim}]")
        if not np.all(np.isfinite(d)):
            raise AlgorithmError(f"{where}: descriptor contains NaN or inf")
        ok = bool(np.linalg.norm(d) > 0)
        self.cur = _StepState(step=step, stamp_s=float(step if stamp_s is None else stamp_s), image=img,
                              context=context, view=view, descriptor=d, descriptor_ok=ok, timings=timings)
        if not ok:
            self._degrade("descriptor:zero-norm")
        return d

    def descriptor_frame(self, dtype: str) -> bytes:
        """Encode this step's descriptor for the wire and keep the quantised values for scoring."""
        st = self._state()
        frame = DescriptorMessage(self.index, st.step, st.descriptor, dtype).encode()
        st.wire_descriptor = decode(frame).descriptor
        st.bytes_sent["descriptor"] += len(frame)
        return frame

    # ---------------------------------------------------------------- 3. gate
    def score_descriptor(self, other: str, descriptor: np.ndarray | None) -> float:
        """Cosine score against a received descriptor; records the gate decision.

        ``descriptor`` None means its message did not arrive. Returns NaN when no
        score can be computed (the gate stays closed and the reason is kept).
        """
        st = self._state()
        t0 = time.perf_counter()
        own = st.wire_descriptor if st.wire_descriptor is not None else st.descriptor
        score, reason = float("nan"), ""
        if descriptor is None:
            reason = "descriptor-missing"
        elif not st.descriptor_ok:
            reason = "own-descriptor-degenerate"
        else:
            d = np.asarray(descriptor, dtype=np.float32).ravel()
            if d.size != own.size:
                self._degrade("descriptor:wrong-length")
                reason = "descriptor-length-mismatch"
            elif not np.all(np.isfinite(d)) or not np.any(d):
                self._degrade("descriptor:other-zero-norm")
                reason = "other-descriptor-degenerate"
            else:
                score = cosine(own, d)
        st.scores[other] = score
        if reason:
            st.gate_reason[other] = reason
        st.timings["gate"] += time.perf_counter() - t0
        return score

    def gate_open(self, other: str) -> bool:
        s = self._state().scores.get(other, float("nan"))
        return bool(np.isfinite(s) and s >= self.config.tau)

    def image_reply(self, request: ImageRequest) -> ImageReply | None:
        """Answer an image request of this step with the current image as JPEG."""
        st = self._state()
        if request.step != st.step or request.target != self.index:
            self._degrade("msg:stale-request")
            return None
        if st.reply_cache is None:
            t0 = time.perf_counter()
            st.reply_cache = ImageReply.from_image(self.index, st.step, st.image,
                                                   _intrinsics_tuple(st.context.intrinsics),
                                                   quality=self.config.jpeg_quality)
            st.timings["gate"] += time.perf_counter() - t0
        return st.reply_cache

    def accept_reply(self, other: str, reply: ImageReply) -> View | None:
        """Decode a collaborator's JPEG into a :class:`View` keyed ``(other, step, "jpeg")``.

        The key differs from the owner's ``(other, step)`` because the pixels do
        (JPEG): plug-ins shared by a simulated team may cache per key, and must not
        mix the raw and the decoded image (nor hand one robot what only another has).
        """
        st = self._state()
        if reply.step != st.step:
            self._degrade("msg:stale-reply")
            return None
        t0 = time.perf_counter()
        try:
            img = reply.image_rgb()
        except MessageError:
            self._degrade("msg:undecodable-jpeg")
            st.gate_reason[other] = "reply-undecodable"
            return None
        finally:
            st.timings["gate"] += time.perf_counter() - t0
        fx, fy, cx, cy = reply.intrinsics
        K = None
        if fx > 0 and fy > 0 and np.all(np.isfinite(reply.intrinsics)):
            K = CameraIntrinsics(fx, fy, cx, cy, img.shape[1], img.shape[0])
        view = View(key=(other, reply.step, "jpeg"), image=img, intrinsics=K)
        st.collab_views[other] = view
        return view

    # ---------------------------------------------------------------- 4. joint pass
    def joint_pass(self) -> BackboneOutput:
        """ONE backbone pass over ``[current] + keyframes (newest first) (+ previous frame) + collaborators``."""
        st = self._state()
        kfs = self.memory.newest_first()
        # metric depth priors for backbones that use them: each keyframe's reference, and the
        # current frame's when it is computed anyway (no keyframe yet: the scale needs it;
        # track_previous: the next step needs it)
        need_cur = not kfs or self.config.track_previous
        if need_cur:
            st.view = dataclasses.replace(st.view, depth_m=self._current_depth())
        views = [st.view] + [View(kf.key, kf.image, kf.intrinsics, kf.depth_ref_m) for kf in kfs]
        prev = self.previous
        st.prev_index = None
        if self.config.track_previous and prev is not None and kfs and prev.view.key != kfs[0].key:
            st.prev_index = len(views)
            views.append(prev.view)
        for other, v in st.collab_views.items():
            st.collab_index[other] = len(views)
            views.append(v)
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
                self._degrade("backbone:non-finite-pose")
        out.valid = valid
        st.out = out
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
            self._degrade("depth:none")
        st.depth_cache = (True, d)
        return d

    def estimate_scale(self) -> float:
        """Memory scale of this pass (NaN when none, not even a previous one)."""
        st = self._state()
        out = st.out
        if out is None:
            raise AlgorithmError(f"{self._where()}: estimate_scale before joint_pass")
        if out.metric_unit and self.config.backbone_metric_unit:
            # not kept as last_scale: that is the fallback of later up-to-scale passes
            st.scale = 1.0
            return st.scale
        kfs = self.memory.newest_first()
        if kfs:
            metric = [kf.depth_ref_m for kf in kfs]
            idx = list(range(1, 1 + len(kfs)))
        else:
            metric = [self._current_depth()]
            idx = [0]
        t0 = time.perf_counter()
        est = recover_scale(metric, [out.depth[k] if out.valid[k] else None for k in idx],
                            [out.depth_conf[k] for k in idx], min_pixels=self.config.min_scale_pixels)
        st.timings["scale"] += time.perf_counter() - t0
        for _, reason in est.skipped:
            self._degrade(f"scale:skipped-{reason}")
        if est.ok:
            st.scale = self.last_scale = est.scale
        elif np.isfinite(self.last_scale):
            st.scale = self.last_scale
            self._degrade("scale:fallback-last")
        elif self.config.unit_scale_without_depth:
            st.scale = 1.0
            self._degrade("scale:unit-no-depth")
        else:
            st.scale = float("nan")
            self._degrade("scale:unavailable")
        return st.scale

    # ---------------------------------------------------------------- 6. ego-motion
    def update_odometry(self) -> np.ndarray:
        """``X_t`` through the reference view, the previous frame or the newest keyframe the
        pass placed; see module doc."""
        st = self._state()
        out = st.out
        if out is None:
            raise AlgorithmError(f"{self._where()}: update_odometry before joint_pass")
        kfs = self.memory.newest_first()
        if not kfs:
            st.ego_status = "first" if self.last_step is None else "no-keyframe"
            if st.ego_status == "no-keyframe":
                self._degrade("ego:no-keyframe")
            return self.X
        if not out.valid[0]:
            st.ego_status = "current-invalid"
        elif not np.isfinite(st.scale):
            st.ego_status = "no-scale"
        else:
            # pass index -> odometry pose of that view, in the order they are tried: the view
            # the backbone measured the current one against (chaining through a view it placed
            # from there adds that placement's error), the previous frame, keyframes newest first
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
                    self.X = ego_motion(X_s, out.T_frame_cam[s], out.T_frame_cam[0], st.scale)
                    st.ego_status = "ok"
                    if s != ref and s != p and s > 1:
                        self._degrade("ego:older-keyframe")
                    return self.X
            st.ego_status = "keyframes-invalid"
        self._degrade("ego:no-estimate")
        return self.X

    def pose_frame(self) -> bytes:
        st = self._state()
        frame = PoseMessage(self.index, st.step, self.X).encode()
        st.bytes_sent["pose"] += len(frame)
        return frame

    # ---------------------------------------------------------------- 8. relative poses
    def note_pose(self, other: str, step: int, X_j: np.ndarray) -> None:
        """Remember robot ``other``'s broadcast odometry pose."""
        self.poses[other] = (int(step), _pose(X_j, f"{self._where()}: pose of robot {other}"))

    def relative(self, other: str) -> tuple[str, np.ndarray | None, str, int]:
        """This step's estimate of ``T_cj_ci`` for robot ``other``.

        Returns ``(source, T_cj_ci or None, reason, anchor_step)``.
        """
        st = self._state()
        out = st.out
        t0 = time.perf_counter()
        try:
            pose = self.poses.get(other)
            fresh = pose is not None and pose[0] == st.step
            reason = ""
            if self.gate_open(other):
                k = st.collab_index.get(other)
                if k is None:
                    reason = st.gate_reason.get(other, "reply-missing")
                elif not out.valid[k]:
                    reason = "collaborator-view-not-placed"
                elif not out.valid[0]:
                    reason = "own-view-not-placed"
                elif not np.isfinite(st.scale):
                    reason = "no-scale"
                else:
                    T = direct_relative(out.T_frame_cam[0], out.T_frame_cam[k], st.scale)
                    if fresh:
                        self.anchors[other] = Anchor(st.step, T, self.X.copy(), pose[1].copy())
                        return "direct", T, "", st.step
                    self._degrade("anchor:not-stored-pose-missing")
                    return "direct", T, "anchor-not-stored: pose message missing", st.step
            else:  # closed; say why when there was no score at all (lost, blank, mismatched)
                reason = st.gate_reason.get(other, "")
                if not self.config.propagate:
                    return "none", None, reason or "gate-closed", -1
            if not self.config.propagate:
                return "none", None, reason, -1
            anchor = self.anchors.get(other)
            if anchor is None:
                return "none", None, "; ".join(r for r in (reason, "no-anchor") if r), -1
            if pose is None:
                return "none", None, "; ".join(r for r in (reason, "no-pose-of-other") if r), -1
            if not fresh:
                self._degrade("pose:stale")
                reason = "; ".join(r for r in (reason, "stale-pose") if r)
            T = propagate_relative_pose(anchor.T_cj_ci, anchor.X_i, self.X, anchor.X_j, pose[1])
            return "propagated", T, reason, anchor.step
        finally:
            st.timings["propagation"] += time.perf_counter() - t0

    # ---------------------------------------------------------------- 9. memory
    def manage_memory(self) -> bool:
        """Keyframe rule and tracking reference; returns whether the current frame became a keyframe."""
        st = self._state()
        st.keyframe = self._keyframe_rule()
        self._keep_previous()
        return st.keyframe

    def _keyframe_rule(self) -> bool:
        st = self._state()
        out = st.out
        if not st.descriptor_ok:
            return False  # a blank frame (already counted) is never worth keeping
        if len(self.memory) and (out is None or not out.valid[0]):
            return False  # a view the backbone cannot place would only break later passes
        if st.ego_status == "keyframes-invalid":
            self.memory.clear()
            self._degrade("memory:reinit")
            insert = True
        else:
            insert, _, _, _ = self.memory.decide(st.descriptor, st.step)
        if insert:
            self.memory.insert(Keyframe(step=st.step, key=st.view.key, descriptor=st.descriptor,
                                        image=st.image, intrinsics=st.context.intrinsics,
                                        T_odom_cam=self.X.copy(), depth_ref_m=self._current_depth()))
        return bool(insert)

    def _keep_previous(self) -> None:
        """Remember this frame as next step's tracking reference when its pose is an estimate."""
        st = self._state()
        self.previous = None
        if not self.config.track_previous or not st.descriptor_ok:
            return
        placed = st.ego_status == "ok" or (st.ego_status == "first" and st.out is not None)
        if placed:  # joint_pass attached this frame's depth to st.view (track_previous)
            self.previous = _Previous(step=st.step, view=st.view, T_odom_cam=self.X.copy())

    def record(self) -> RobotRecord:
        st = self._state()
        self.last_step = st.step
        return RobotRecord(step=st.step, stamp_s=st.stamp_s, robot=self.robot_id, T_odom_cam=self.X.copy(),
                           scale=float(st.scale), n_keyframes=len(self.memory), keyframe=st.keyframe,
                           bytes_sent=dict(st.bytes_sent), timings_s={k: float(v) for k, v in st.timings.items()},
                           degradations=list(st.degradations))


# --------------------------------------------------------------------------- the team
class Team:
    """N robots, one :class:`~cerpe.transport.Channel`, the three plug-ins, a config.

    Args:
        robot_ids: robot names in a fixed order (index = wire sender id).
        descriptor, backbone, depth: the plug-ins (:mod:`cerpe.protocols`), shared.
        config: parameters; thresholds are resolved against the descriptor's
            calibration (see :class:`CerpeConfig`).
        channel: the medium; a lossless one by default.
    """

    def __init__(self, robot_ids: Sequence[str], descriptor: DescriptorEncoder, backbone: PoseBackbone,
                 depth: MetricDepthSource, config: CerpeConfig | None = None,
                 channel: Channel | None = None) -> None:
        ids = [str(r) for r in robot_ids]
        if not ids or len(set(ids)) != len(ids) or len(ids) >= 2**16:
            raise AlgorithmError(f"team: robot ids must be unique and non-empty, got {ids}")
        self.robot_ids = ids
        self.descriptor, self.backbone, self.depth = descriptor, backbone, depth
        self.config = (config or CerpeConfig()).resolved(getattr(descriptor, "thresholds", None))
        self.channel = channel if channel is not None else Channel()
        self.reset()

    def reset(self) -> None:
        """Forget everything (memory, odometry, anchors): a new encounter starts."""
        for r in self.robot_ids:
            self.channel.attach(r)
        self.agents = [RobotAgent(r, i, self.config, self.descriptor, self.backbone, self.depth)
                       for i, r in enumerate(self.robot_ids)]
        self._by_index = {i: r for i, r in enumerate(self.robot_ids)}
        for r in self.robot_ids:  # a fresh encounter starts with empty inboxes
            self.channel.receive(r)

    def agent(self, robot_id: str) -> RobotAgent:
        for a in self.agents:
            if a.robot_id == robot_id:
                return a
        raise AlgorithmError(f"team: no robot {robot_id!r}")

    def _inbox(self, a: RobotAgent) -> list:
        """Robot ``a``'s decoded messages; lost/garbled frames are counted on ``a``."""
        d = self.channel.receive(a.robot_id)
        for what in d.degradations:
            a._degrade(what)
        return [msg for _, msg in d.messages]

    def _sender(self, a: RobotAgent, idx: int) -> str | None:
        r = self._by_index.get(idx)
        if r is None:
            a._degrade("msg:unknown-sender")
        return r

    def step(self, images: Sequence[np.ndarray], contexts: Sequence[FrameContext],
             stamps_s: Sequence[float] | None = None) -> StepResult:
        """One synchronous round for all robots; see the module docstring."""
        n = len(self.agents)
        if len(images) != n or len(contexts) != n:
            raise AlgorithmError(f"team step: {len(images)} images and {len(contexts)} contexts for {n} robots")
        steps = {int(c.step) for c in contexts}
        if len(steps) != 1:
            raise AlgorithmError(f"team step: robots are at different steps {sorted(steps)}")
        t = steps.pop()
        ch, cfg, A = self.channel, self.config, self.agents

        # 1-2. describe and broadcast
        for k, a in enumerate(A):
            a.begin_step(images[k], contexts[k], None if stamps_s is None else stamps_s[k])
        for a in A:
            ch.broadcast(a.robot_id, "descriptor", a.descriptor_frame(cfg.descriptor_dtype))
        # 3. gate: score, request, reply
        for a in A:
            got: dict[str, np.ndarray] = {}
            for msg in self._inbox(a):
                if isinstance(msg, DescriptorMessage) and msg.step == t:
                    r = self._sender(a, msg.sender)
                    if r is not None and r != a.robot_id:
                        got[r] = msg.descriptor
            for b in A:
                if b is not a:
                    a.score_descriptor(b.robot_id, got.get(b.robot_id))
        pair_bytes: Counter = Counter()
        for a in A:
            for b in A:
                if b is not a and a.gate_open(b.robot_id):
                    frame = ImageRequest(a.index, t, b.index).encode()
                    nb = ch.send(a.robot_id, "request", frame, b.robot_id)
                    a.cur.bytes_sent["request"] += nb
                    pair_bytes[(a.robot_id, b.robot_id)] += nb
        requests: list[tuple[RobotAgent, str, ImageRequest]] = []
        for b in A:  # all requests are read before any reply is sent (one inbox per robot)
            for msg in self._inbox(b):
                if isinstance(msg, ImageRequest):
                    r = self._sender(b, msg.sender)
                    if r is not None:
                        requests.append((b, r, msg))
        for b, r, msg in requests:
            reply = b.image_reply(msg)
            if reply is not None:
                nb = ch.send(b.robot_id, "reply", reply.encode(), r)
                b.cur.bytes_sent["reply"] += nb
                pair_bytes[(r, b.robot_id)] += nb
        for a in A:
            for msg in self._inbox(a):
                if isinstance(msg, ImageReply):
                    r = self._sender(a, msg.sender)
                    if r is not None and a.gate_open(r):
                        a.accept_reply(r, msg)
        # 4-6. joint pass, scale, odometry; 7. pose broadcast
        for a in A:
            a.joint_pass()
            a.estimate_scale()
            a.update_odometry()
        for a in A:
            ch.broadcast(a.robot_id, "pose", a.pose_frame())
        for a in A:
            a.note_pose(a.robot_id, t, a.X)
            for msg in self._inbox(a):
                if isinstance(msg, PoseMessage) and msg.step == t:
                    r = self._sender(a, msg.sender)
                    if r is not None:
                        a.note_pose(r, msg.step, msg.T_odom_cam)
        # 8. relative poses
        pairs: list[PairRecord] = []
        for a in A:
            for b in A:
                if b is a:
                    continue
                source, T, reason, anchor_step = a.relative(b.robot_id)
                pairs.append(PairRecord(
                    step=t, stamp_s=a.cur.stamp_s, ego=a.robot_id, other=b.robot_id,
                    gate_score=float(a.cur.scores.get(b.robot_id, float("nan"))),
                    gate_open=a.gate_open(b.robot_id), source=source, T_cj_ci=T, reason=reason,
                    bytes_pair=int(pair_bytes[(a.robot_id, b.robot_id)]), anchor_step=anchor_step))
        # 9. memory
        robots = []
        for a in A:
            a.manage_memory()
            robots.append(a.record())
        return StepResult(step=t, pairs=pairs, robots=robots)

    def run_encounter(self, encounter: Encounter, progress: bool = False, seed: int = 0,
                      max_steps: int | None = None) -> Iterator[StepResult]:
        """Reset and walk ``encounter`` step by step (images and sensor depth loaded lazily)."""
        if encounter.robot_ids != self.robot_ids:
            raise AlgorithmError(f"encounter {encounter.name}: robots {encounter.robot_ids} "
                                 f"differ from the team's {self.robot_ids}")
        self.reset()
        T = encounter.n_steps if max_steps is None else min(encounter.n_steps, int(max_steps))
        steps: Iterator[int] = iter(range(T))
        if progress:
            from tqdm.auto import tqdm

            steps = iter(tqdm(range(T), desc=f"cerpe {encounter.name}", unit="step"))
        for t in steps:
            images = [r.image(t) for r in encounter.robots]
            contexts = [FrameContext(r.robot_id, t, r.intrinsics, r.depth_m(t), seed) for r in encounter.robots]
            yield self.step(images, contexts, [float(r.stamps_s[t]) for r in encounter.robots])


def run_encounter(encounter: Encounter, descriptor: DescriptorEncoder, backbone: PoseBackbone,
                  depth: MetricDepthSource, config: CerpeConfig | None = None, channel: Channel | None = None,
                  progress: bool = False, seed: int = 0) -> Iterator[StepResult]:
    """Build a :class:`Team` for ``encounter``'s robots and walk it."""
    team = Team(encounter.robot_ids, descriptor, backbone, depth, config, channel)
    yield from team.run_encounter(encounter, progress=progress, seed=seed)
