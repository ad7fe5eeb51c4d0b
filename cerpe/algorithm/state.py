"""What one robot holds during a step (:class:`StepState`) and between steps besides its memory (:class:`Previous`)."""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from ..messages import ImageReply
from ..protocols import BackboneOutput, FrameContext, View


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
    directs: dict[str, tuple[list, str]] = field(default_factory=dict)  # peer -> own direct estimates, reason
    shared: dict[str, tuple] = field(default_factory=dict)  # peer -> its estimate of this robot, as this robot's
    scale: float = float("nan")
    metric_scale: bool = True  # False: s = 1 for want of metric depth (unit_scale_without_depth)
    ego_status: str = ""
    keyframe: bool = False
    timings: Counter = field(default_factory=Counter)
    degradations: list[str] = field(default_factory=list)
    bytes_sent: Counter = field(default_factory=Counter)
    reply_cache: ImageReply | None = None
    depth_cache: tuple[bool, np.ndarray | None] = (False, None)


@dataclass
class PairInfo:
    """How this step's direct estimate for one peer came about (pair record columns).

    ``direct_via``: step of the own view it was registered through (-1: the current
    frame or the joint pass; -2: the peer's estimate, shared, ``CerpeConfig.share_estimates``); ``verdict``: what anchor verification said (``""``
    without a direct estimate, ``"unchecked"`` with ``verify_anchors=False``);
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
