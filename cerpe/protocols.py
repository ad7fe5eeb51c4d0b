"""The three plug-in roles of CERPE as small typed protocols.

Algorithm code depends only on these; concrete models live in ``cerpe.backbones``
and are constructed from a config by ``cerpe.backbones.build``.

* :class:`DescriptorEncoder` -- image -> fixed-size, L2-normalised global descriptor.
* :class:`PoseBackbone` -- a batch of views -> per-view camera-to-frame poses in one
  shared, up-to-scale frame, plus per-view depth maps with confidence.
* :class:`MetricDepthSource` -- a frame -> metric depth (possibly sparse).

Failures that are part of normal operation (no overlap, no texture, degenerate
geometry) are *returned* (``ok=False`` / per-view ``valid=False`` with a reason),
never raised: a robot must keep going. Programming errors and malformed input
raise :class:`BackboneError`.
"""
from __future__ import annotations

from .errors import CerpeError
from dataclasses import dataclass, field
from typing import Any, Hashable, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from .scene import CameraIntrinsics


class BackboneError(CerpeError, ValueError):
    """Malformed input to a plug-in (wrong shape, dtype, descriptor length...)."""


# BackboneOutput.reasons of a collaborator view whose placement by keypoints the images contradict
REASON_APPEARANCE = "appearance-mismatch"
# grey-level standard deviation (0-255 scale) below which an image is blank (black, white, constant grey):
# the algorithm broadcasts a zero descriptor for it, and plug-ins describe and match nothing in it
BLANK_STD = 2.0


@dataclass
class View:
    """One image handed to a backbone.

    Attributes:
        key: stable identifier ``(robot_id, step)`` (or any hashable); backbones may
            cache per-key work (features, 3D points) across calls.
        image: ``[H,W,3] uint8`` RGB.
        intrinsics: known intrinsics when the robot has them (collaborator images
            carry theirs in the image reply); a backbone may ignore them.
        depth_m: optional metric depth prior ``[H*,W*] float32`` in metres (0 =
            unknown; any resolution, resampled to the image by nearest neighbour),
            e.g. a keyframe's sensor or metric-network depth. VGGT ignores it; the
            offline geometry backbone anchors its points on it (see
            :mod:`cerpe.backbones.offline`). Outputs stay "up to scale" either way.
        memo: what the backbone said about this view when it was the current view of
            an earlier pass (:attr:`BackboneOutput.memos`), handed back unchanged by
            the robot that keeps the view (keyframe, previous frame); None when there
            is none. Opaque to the algorithm. A backbone keeps no state between calls:
            what it needs to remember about a robot's past goes out in a memo and
            comes back in with the view, so a pass depends on its views alone.
        role: what the view is to the robot running the pass: ``"current"``,
            ``"keyframe"``, ``"previous"`` (own frames) or ``"collaborator"`` (an image
            another robot sent); None when the caller does not say. A backbone may
            treat collaborator views differently (a costlier cross-robot matcher).
        depth_rel_sigma: the relative sigma of ``depth_m``'s scale and low-frequency shape
            as its depth source reports it (:attr:`MetricDepthSource.rel_sigma`: 0 for a
            depth sensor, ~0.1 for a monocular network); None when not known. The offline
            backbone corrects a per-frame scale only above a threshold
            (``frame_scale_min_rel_sigma``); it never asks which source made the depth.
        try_hard: for a collaborator view, the robot asks for the backbone's costliest
            registration of it. It does so when the gate opened for it and the robot holds no
            anchor of the sender yet (first contact, or a pair that lost its anchor); tries
            that failed back off (:func:`cerpe.algorithm.policy.try_hard`). A backbone may
            ignore it; the offline backbone's ``cross.fallback`` reads it.
        pose_wanted: False: in a pass in metres (:attr:`BackboneOutput.metric_unit`) whose
            ``reference`` is another view than the current one, the caller reads this view's pose
            only if it is that reference. The agent says so for its keyframes and previous frame in
            a pass without collaborators: ego-motion chains through the reference, and a metric pass
            needs no scale. A backbone may then leave the view unplaced in such a pass (``valid``
            False, reason ``not-wanted``) to save the time; placing it anyway is right too (VGGT
            places every view jointly).
    """

    key: Hashable
    image: np.ndarray
    intrinsics: CameraIntrinsics | None = None
    depth_m: np.ndarray | None = None
    memo: Mapping[str, Any] | None = None
    role: str | None = None
    depth_rel_sigma: float | None = None
    try_hard: bool = False
    pose_wanted: bool = True


@dataclass(frozen=True)
class Registration:
    """One independent placement of a view against ONE other view of the pass.

    The offline backbone registers each collaborator image against each of the
    robot's own views that carries a depth prior (current frame, previous frame,
    keyframes). So the algorithm can (a) place a collaborator seen only from an
    older keyframe, through that keyframe's odometry pose, and (b) verify a
    direct estimate by the agreement of two registrations through different views.

    Attributes:
        via: index (in the pass) of the view it was registered against.
        T_via_cam: ``[4,4]`` pose of the registered view in the ``via`` view's
            camera (maps its camera points into ``via``'s camera), in the pass's
            translation unit (metres when :attr:`BackboneOutput.metric_unit`).
        inliers: verified correspondences that support it (RANSAC inliers).
        matches: putative matches it was found among (inliers / matches is the
            inlier ratio).
    """

    via: int
    T_via_cam: np.ndarray
    inliers: int
    matches: int = 0


@dataclass
class BackboneOutput:
    """Result of one joint pass over ``S`` views, in the order they were given.

    Attributes:
        T_frame_cam: ``[S,4,4]`` camera-to-frame poses in one shared frame whose
            translation unit is arbitrary (consistent with ``depth``). Rows of an
            invalid view are NaN.
        valid: ``[S] bool``; False where the backbone could not place the view.
        depth: ``S`` arrays ``[H_s,W_s] float32`` in the same unit as the
            translations, 0 where unknown (may be sparse).
        depth_conf: ``S`` arrays like ``depth``, >= 0, 0 where invalid.
        intrinsics: ``S`` intrinsics (estimated or passed through), None if unknown.
        reasons: per-view reason when not valid (``""`` when valid); :data:`REASON_APPEARANCE`
            for a collaborator view placed by the keypoints whose placement the images
            themselves contradict (the algorithm counts it ``direct:appearance-mismatch``).
        timings_s: stage name -> seconds spent in this pass.
        extra: other per-pass figures a backbone reports (e.g. peak VRAM bytes),
            name -> number; may be empty.
        metric_unit: True when the translation unit of this pass is already the metre
            (the backbone anchored it on the views' metric depth priors); the scale
            step then has nothing to recover (``scale.metric_unit``).
            Up-to-scale backbones (VGGT) leave it False.
        reference: index of the view against which the current view (index 0) was
            measured most directly (the offline backbone's depth-prior view, whose
            relative pose it refines densely), or None when the pass places all views
            jointly (VGGT). Ego-motion chains through this view when it is a keyframe
            or the previous frame.
        memos: per view, what the backbone wants handed back with that view in later
            passes (:attr:`View.memo`), or None; the algorithm stores the current
            view's (index 0) with the frame it keeps. Empty: no memos.
        registrations: view index -> its independent :class:`Registration` s against
            single other views of the pass, most inliers first (offline backbone:
            collaborator views). Empty for backbones that place all views jointly
            (VGGT); the algorithm then uses ``T_frame_cam`` alone.
        support: ``[S]`` per view, the verified correspondences that placed it in
            ``T_frame_cam`` (offline backbone: its 2D-3D inliers in the joint pass; a
            view placed through a registration: that registration's inliers), -1 where
            unknown or unplaced. The algorithm records a joint-pass direct estimate's
            support as its inliers (the graph's per-estimate noise can read it).
    """

    T_frame_cam: np.ndarray
    valid: np.ndarray
    depth: list[np.ndarray]
    depth_conf: list[np.ndarray]
    intrinsics: list[CameraIntrinsics | None] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)
    extra: dict[str, float] = field(default_factory=dict)
    metric_unit: bool = False
    reference: int | None = None
    memos: list[Mapping[str, Any] | None] = field(default_factory=list)
    registrations: dict[int, list[Registration]] = field(default_factory=dict)
    support: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        S = len(self.valid)
        if not self.support:
            self.support = [-1] * S
        elif len(self.support) != S:
            raise BackboneError(f"BackboneOutput: {len(self.support)} support counts for {S} views")
        if self.T_frame_cam.shape != (S, 4, 4):
            raise BackboneError(f"BackboneOutput: T_frame_cam {self.T_frame_cam.shape} for {S} views")
        if len(self.depth) != S or len(self.depth_conf) != S:
            raise BackboneError("BackboneOutput: one depth and one confidence map per view required")
        if not self.reasons:
            self.reasons = ["" for _ in range(S)]
        if not self.intrinsics:
            self.intrinsics = [None for _ in range(S)]
        if not self.memos:
            self.memos = [None for _ in range(S)]
        elif len(self.memos) != S:
            raise BackboneError(f"BackboneOutput: {len(self.memos)} memos for {S} views")
        for k, regs in self.registrations.items():
            if not 0 <= k < S or any(not 0 <= r.via < S or r.via == k for r in regs):
                raise BackboneError(f"BackboneOutput: registration of view {k} names a view outside 0..{S - 1} "
                                    "or itself")


@runtime_checkable
class DescriptorEncoder(Protocol):
    """Image -> fixed-size global descriptor (the gate and memory use it).

    ``describe`` returns ``[dim] float32``, L2-normalised. Thresholds calibrated
    for this descriptor live in ``thresholds`` (keys ``tau``, ``tau_m``, ``tau_k``).

    Images without usable texture (blank, black, constant grey): an encoder may
    define ``flags(view) -> frozenset[str]``, called by the algorithm right after
    ``describe(view)``. ``"low-texture"`` in it marks the frame blank (the gate
    stays closed, the frame is never a keyframe nor a tracking reference, and it
    is counted). A zero descriptor is treated the same way.
    """

    dim: int
    thresholds: dict[str, float]

    def describe(self, view: View) -> np.ndarray: ...


@runtime_checkable
class PoseBackbone(Protocol):
    """Joint multi-view pass: ``views`` -> :class:`BackboneOutput`.

    The first view is the robot's current image, then its memory keyframes
    (newest first), then collaborator images. The output frame is arbitrary and
    may differ between calls.
    """

    def infer(self, views: Sequence[View]) -> BackboneOutput: ...

    # Optional: ``serve_robots(n)``, called by a team of ``n`` robots sharing one backbone in one
    # process, lets per-image caches grow with the team; it must not change any result.


@runtime_checkable
class MetricDepthSource(Protocol):
    """Metric depth for a robot's own frame: ``[H,W] float32`` metres, 0 = unknown.

    Returns None when the source has nothing for this frame (the scale step then
    skips it and counts it). Optionally ``rel_sigma: float``: the relative sigma of a depth
    map's scale and low-frequency shape, about 0.1 for a monocular network, ~0 for a depth
    sensor. That error is what a whole placement's points share, so it moves a camera placed
    on them along its line of sight; per-pixel noise averages out. The pose graph's noise model
    reads it (:class:`cerpe.algorithm.graph.DirectEstimate`); absent: unknown. Optionally
    ``metric: bool``: False for a source that never has metric depth (no depth at all). The
    algorithm then takes s = 1 (counted ``scale:unit-no-depth``) instead of giving up. Optionally
    ``sensor: bool``: True for depth a sensor hands over with the frame (a recorded map, or its
    simulation). What computing it costs here is then the reader's or the simulation's, not the
    robot's: the step times it as the ``sensor`` part of ``scale``, and ``cerpe bench`` leaves it out
    of the robot's step.
    """

    name: str

    def depth_m(self, view: View, frame: "FrameContext") -> np.ndarray | None: ...


@dataclass
class FrameContext:
    """What a depth source may know about a robot's own frame beyond its pixels.

    ``sensor_depth_m`` is the dataset's metric depth for this frame when there is
    one (RGB-D, projected LiDAR, or a renderer's exact depth for simulated
    sources); a monocular network ignores it.
    """

    robot_id: str
    step: int
    intrinsics: CameraIntrinsics | None
    sensor_depth_m: np.ndarray | None = None
    seed: int = 0
