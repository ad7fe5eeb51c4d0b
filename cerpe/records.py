"""What one step of the algorithm leaves behind: per ordered pair and per robot.

These records are the only interface between the algorithm and everything that
evaluates, stores or plots it (``cerpe.pipeline``, notebooks). They are plain
data; :func:`PairRecord.as_row` / :func:`RobotRecord.as_row` flatten them to the
columns of ``steps.csv`` / ``robots.csv`` (see ``docs/formats.md``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .geometry import pose_cov_sigmas, se3_to_tq_xyzw
from .reasons import check_degradations, check_reason

Source = Literal["direct", "propagated", "none"]
SOURCES: tuple[str, ...] = ("direct", "propagated", "none")

STAGES: tuple[str, ...] = ("encode", "descriptor", "gate", "backbone", "scale", "propagation", "graph")


def _pose_cols(prefix: str, T: np.ndarray | None) -> dict[str, float]:
    names = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
    if T is None or not np.all(np.isfinite(T)):
        return {f"{prefix}_{n}": float("nan") for n in names}
    t, q = se3_to_tq_xyzw(T)
    return {f"{prefix}_{n}": float(v) for n, v in zip(names, [*t, *q])}


@dataclass
class PairRecord:
    """Robot ``ego`` (the paper's i) about robot ``other`` (j) at one step.

    Attributes:
        step: step index within the encounter.
        stamp_s: capture time of the ego image.
        ego, other: robot ids.
        gate_score: cosine similarity of the two robots' current descriptors (the
            paper's gate score, what gate-quality metrics read); NaN if the other's
            descriptor message was lost or garbled.
        gate_open: whether the gate opened: ``gate_score >= tau``, or with ``gate.memory_aware``
            ``gate_score_memory >= tau`` (the ego requested the other's image unless
            ``request_skipped``; with the policy ``always`` it requested it in any case).
        source: ``direct`` (from this step's pass), ``propagated`` (an anchor moved
            by both robots' ego-motion) or ``none``.
        T_cj_ci: the estimate of the paper's ``T_ij`` (metric), None when ``none``.
        reason: tokens of :data:`cerpe.reasons.REASONS` joined by ``"; "``. They say why there
            is no direct estimate although the gate was open, or no estimate at all. Or they say
            ``unverified`` (a direct estimate nothing confirmed yet, or its propagation), or
            ``direct-rejected`` (the direct estimate disagreed with the anchor, which is
            propagated instead). ``""`` otherwise. Numbers are columns of their own, never in the reason.
        bytes_pair: bytes of the image request and image reply for this pair.
        anchor_step: step of the anchor a propagated estimate comes from (-1 if none).
        gate_score_memory: best cosine of the other's descriptor against the ego's
            current descriptor and its keyframes' (NaN when not scored).
        gate_via: step of the keyframe that gave ``gate_score_memory``; -1 for the
            current frame.
        direct_via: step of the own view the direct estimate was registered
            through; -1 for the current frame or the joint pass (or no estimate).
        anchor_verdict: what anchor verification said about this step's direct
            estimate: ``verified``, ``accepted``, ``unverified``, ``rejected``,
            ``replaced``, ``unchecked`` (``anchors.verify: false``), ``""`` (none).
        check_rot_rad, check_trans_m: disagreement of the direct estimate with what
            it was checked against (the propagated anchor, a second registration,
            an earlier candidate); NaN when nothing was compared.
        cov: ``[6,6]`` covariance of ``T_cj_ci`` over ``[rotation, translation]`` of a
            right perturbation (the error in camera i's frame; :mod:`cerpe.geometry`,
            "pose covariances"); None for methods without one. ``as_row`` gives its
            ``sigma_pos_m`` and ``sigma_rot_rad`` (predicted RMS errors; NaN without).
        T_direct: this step's direct estimate as the pass gave it, whatever anchor
            verification said of it (None without one); ``dir_*`` columns.
        direct_inliers: inliers of the registration behind ``T_direct`` (-1: unknown or none).
        switch: with ``backend="graph"``, what the switch (the paper's CERPE) said at this
            step, ``(source, T_cj_ci, reason, anchor_step)``: the graph reads nothing back
            into the algorithm, so one pass yields both methods' records. Not a column.
        request_skipped: the gate opened but the request policy did not ask for the image
            (``policy.mode: pays``: the pair's anchor was fresh and certain).
    """

    step: int
    stamp_s: float
    ego: str
    other: str
    gate_score: float
    gate_open: bool
    source: Source
    T_cj_ci: np.ndarray | None
    reason: str = ""
    bytes_pair: int = 0
    anchor_step: int = -1
    gate_score_memory: float = float("nan")
    gate_via: int = -1
    direct_via: int = -1
    anchor_verdict: str = ""
    check_rot_rad: float = float("nan")
    check_trans_m: float = float("nan")
    cov: np.ndarray | None = None
    T_direct: np.ndarray | None = None
    direct_inliers: int = -1
    switch: tuple | None = None
    request_skipped: bool = False

    def __post_init__(self) -> None:
        check_reason(self.reason)  # a closed vocabulary: cerpe.reasons.REASONS

    def as_row(self) -> dict:
        row = {
            "step": self.step, "stamp_s": self.stamp_s, "ego": self.ego, "other": self.other,
            "gate_score": self.gate_score, "gate_open": bool(self.gate_open), "source": self.source,
            "reason": self.reason, "bytes_pair": int(self.bytes_pair), "anchor_step": self.anchor_step,
            "gate_score_memory": self.gate_score_memory, "gate_via": int(self.gate_via),
            "direct_via": int(self.direct_via), "anchor_verdict": self.anchor_verdict,
            "check_rot_rad": self.check_rot_rad, "check_trans_m": self.check_trans_m,
        }
        row.update(_pose_cols("est", self.T_cj_ci))
        # per block: a covariance may know the rotation only (NaN translation block: scale unknown)
        pos, rot = pose_cov_sigmas(self.cov) if self.cov is not None else (float("nan"), float("nan"))
        row.update({"sigma_pos_m": float(pos), "sigma_rot_rad": float(rot), "direct_inliers": int(self.direct_inliers)})
        row.update(_pose_cols("dir", self.T_direct))
        row["request_skipped"] = bool(self.request_skipped)
        return row


@dataclass
class RobotRecord:
    """One robot at one step.

    Attributes:
        T_odom_cam: the broadcast metric odometry pose ``X_i^t``.
        scale: the memory scale ``s`` used at this step (NaN if none could be computed).
        n_keyframes: memory size after this step's memory management.
        keyframe: whether this step's image became a keyframe.
        bytes_sent: bytes this robot put on the wire at this step, by message kind
            (``descriptor``, ``pose``, ``request``, ``reply``).
        timings_s: seconds per stage (see :data:`STAGES`).
        degradations: counted, logged problems of this step (names of :data:`cerpe.reasons.DEGRADATIONS`:
            ``"depth:none"``, ``"msg:garbled"``...).
        cpu_s: CPU seconds per stage (and per part of a stage, as in ``parts_s``) of the thread that
            ran it (``cerpe bench``; not written to ``robots.csv``, whose timings are the wall ones).
        parts_s: wall seconds of parts of stages, e.g. ``gate_score`` (the descriptor scores, part of
            ``gate``).
    """

    step: int
    stamp_s: float
    robot: str
    T_odom_cam: np.ndarray
    scale: float
    n_keyframes: int
    keyframe: bool
    bytes_sent: dict[str, int] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    degradations: list[str] = field(default_factory=list)
    cpu_s: dict[str, float] = field(default_factory=dict)
    parts_s: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_degradations(self.degradations)  # a closed vocabulary: cerpe.reasons.DEGRADATIONS

    @property
    def bytes_total(self) -> int:
        return int(sum(self.bytes_sent.values()))

    def as_row(self) -> dict:
        row = {
            "step": self.step, "stamp_s": self.stamp_s, "robot": self.robot, "scale": self.scale,
            "n_keyframes": self.n_keyframes, "keyframe": bool(self.keyframe),
            "bytes_total": self.bytes_total,
            "degradations": ";".join(self.degradations),
        }
        for k in ("descriptor", "pose", "request", "reply", "estimate"):
            row[f"bytes_{k}"] = int(self.bytes_sent.get(k, 0))
        for s in STAGES:
            row[f"t_{s}_s"] = float(self.timings_s.get(s, 0.0))
        row.update(_pose_cols("odom", self.T_odom_cam))
        return row


@dataclass
class StepResult:
    """Everything the team produced at one step."""

    step: int
    pairs: list[PairRecord]
    robots: list[RobotRecord]
