"""Bounded keyframe memory of one robot (paper Sec. III-B, Algorithm 1 "Memory Management").

The rule (paper Eq. keyframe selection): let ``c`` be the cosine similarity of the
current descriptor to the *most recent* keyframe's descriptor, and ``Delta`` the
step gap to it. The current frame becomes a keyframe when the memory is empty or

    (c < tau_m and Delta > delta_k)  or  c < tau_k

and the oldest keyframe is evicted once more than ``capacity`` (the paper's ``L``)
are stored. :func:`should_insert` is the pure decision; :class:`KeyframeMemory`
holds the keyframes.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Hashable, Iterator, Literal, Mapping

import numpy as np

from .errors import CerpeError
from .knobs import Group, KnobError, knob
from .scene import CameraIntrinsics

Branch = Literal["empty", "large-change", "moderate-change", "skip"]


class KeyframeMemoryError(CerpeError, ValueError):
    """Malformed keyframe, configuration or query (names the field at fault)."""


@dataclass(frozen=True)
class MemoryConfig(Group):
    """The keyframe rule's parameters (the paper's ``tau_m``, ``tau_k``, ``Delta_k``, ``L``).

    ``delta_k``: the paper says "fixed" without a value. 3 steps is 0.3 s at the 10 Hz of the CAD
    and OpenMARS data. A multi-view backbone needs baseline between the views it triangulates: at
    urban speeds (5-15 m/s) 0.3 s gives 1.5-4.5 m between keyframes. A memory of 5 then still spans
    only 1.5-2 s, so the newest keyframe (through which ego-motion is composed) stays close to the
    current view. ``tau_m``/``tau_k`` None: the descriptor's calibrated values (the paper's 0.9 / 0.2
    are SALAD's); :class:`KeyframeMemory` needs them resolved.
    """

    tau_m: float | None = knob(None, "similarity to the newest keyframe below which a frame is a moderate change, "
                               "kept after more than delta_k steps (cosine; None: the descriptor's value)",
                               low=-1.0, high=1.0)
    tau_k: float | None = knob(None, "similarity below which a frame is a large change, kept at once (cosine; "
                               "None: the descriptor's value)", low=-1.0, high=1.0)
    delta_k: int = knob(3, "steps a moderate change must be from the newest keyframe to be kept", low=0)
    capacity: int = knob(5, "keyframes kept (the paper's L); the oldest is evicted", low=1)

    def check(self) -> None:
        if self.tau_m is not None and self.tau_k is not None and self.tau_k > self.tau_m:
            raise KnobError(f"memory.tau_k ({self.tau_k}) must not exceed memory.tau_m ({self.tau_m})")


def should_insert(c: float | None, delta: int | None, conf: MemoryConfig) -> tuple[bool, Branch]:
    """The paper's keyframe rule as a pure function.

    Args:
        c: cosine similarity of the current descriptor to the newest keyframe's;
            None when the memory is empty.
        delta: step gap to the newest keyframe (ignored when ``c`` is None).
        conf: thresholds.

    Returns:
        ``(insert, branch)`` with branch ``"empty"``, ``"large-change"``
        (``c < tau_k``; checked first because it needs no gap),
        ``"moderate-change"`` (``c < tau_m and delta > delta_k``) or ``"skip"``.

    Raises:
        KeyframeMemoryError: non-finite ``c`` or a missing/negative ``delta``.
    """
    if c is None:
        return True, "empty"
    if not np.isfinite(c):
        raise KeyframeMemoryError(f"should_insert: similarity c must be finite, got {c}")
    if delta is None or delta < 0:
        raise KeyframeMemoryError(f"should_insert: step gap delta must be >= 0, got {delta}")
    if c < conf.tau_k:
        return True, "large-change"
    if c < conf.tau_m and delta > conf.delta_k:
        return True, "moderate-change"
    return False, "skip"


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    """Cosine similarity of two 1-D vectors; NaN when either has zero norm."""
    a = np.asarray(a, dtype=np.float64).ravel()
    b = np.asarray(b, dtype=np.float64).ravel()
    if a.shape != b.shape:
        raise KeyframeMemoryError(f"cosine: descriptor lengths differ ({a.size} vs {b.size})")
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if not (na > 0 and nb > 0 and np.isfinite(na) and np.isfinite(nb)):
        return float("nan")
    return float(np.clip(a @ b / (na * nb), -1.0, 1.0))


@dataclass
class Keyframe:
    """One stored frame of a robot.

    Attributes:
        step: step index at which it was captured.
        key: the view key the backbone knows it by (``(robot_id, step)``).
        descriptor: ``[D] float32`` global descriptor (non-zero norm).
        image: ``[H,W,3] uint8`` RGB.
        intrinsics: the camera's intrinsics, None when unknown.
        T_odom_cam: ``[4,4]`` the robot's metric odometry pose ``X`` at that step.
        depth_ref_m: ``[H',W'] float32`` metric depth reference (0 = unknown), or
            None when the depth source had nothing for this frame.
        memo: what the backbone said about this frame when it was the current view
            (:attr:`cerpe.protocols.BackboneOutput.memos`), handed back as
            :attr:`cerpe.protocols.View.memo`; None when it said nothing.
    """

    step: int
    key: Hashable
    descriptor: np.ndarray
    image: np.ndarray
    intrinsics: CameraIntrinsics | None
    T_odom_cam: np.ndarray
    depth_ref_m: np.ndarray | None = None
    memo: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        what = f"keyframe {self.key!r}"
        d = np.asarray(self.descriptor, dtype=np.float32)
        if d.ndim != 1 or d.size == 0 or not np.all(np.isfinite(d)) or not np.any(d):
            raise KeyframeMemoryError(f"{what}: descriptor must be a finite, non-zero 1-D vector (shape {d.shape})")
        self.descriptor = d
        img = np.asarray(self.image)
        if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
            raise KeyframeMemoryError(f"{what}: image must be [H,W,3], got shape {img.shape}")
        T = np.asarray(self.T_odom_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise KeyframeMemoryError(f"{what}: T_odom_cam must be a finite 4x4 matrix")
        self.T_odom_cam = T
        if self.depth_ref_m is not None:
            dr = np.asarray(self.depth_ref_m, dtype=np.float32)
            if dr.ndim != 2 or dr.size == 0:
                raise KeyframeMemoryError(f"{what}: depth_ref_m must be 2-D, got shape {dr.shape}")
            self.depth_ref_m = dr


class KeyframeMemory:
    """FIFO of at most ``conf.capacity`` keyframes with the paper's insertion rule."""

    def __init__(self, conf: MemoryConfig | None = None) -> None:
        self.conf = conf or MemoryConfig(tau_m=0.9, tau_k=0.2)
        if self.conf.tau_m is None or self.conf.tau_k is None:
            raise KeyframeMemoryError("keyframe memory: tau_m and tau_k must be resolved (the descriptor's or the "
                                      "paper's values), got None")
        self._frames: deque[Keyframe] = deque()

    def __len__(self) -> int:
        return len(self._frames)

    def __iter__(self) -> Iterator[Keyframe]:
        """Oldest first."""
        return iter(self._frames)

    def newest_first(self) -> list[Keyframe]:
        return list(reversed(self._frames))

    def newest(self) -> Keyframe:
        if not self._frames:
            raise KeyframeMemoryError("keyframe memory is empty: no newest keyframe")
        return self._frames[-1]

    def decide(self, descriptor: np.ndarray, step: int) -> tuple[bool, Branch, float, int | None]:
        """Apply :func:`should_insert` to a candidate.

        Returns ``(insert, branch, c, delta)``; ``c`` is NaN and ``delta`` None for
        an empty memory. A zero-norm candidate descriptor raises (callers skip
        degenerate frames before asking).
        """
        if not self._frames:
            return True, "empty", float("nan"), None
        kf = self._frames[-1]
        c = cosine(descriptor, kf.descriptor)
        if not np.isfinite(c):
            raise KeyframeMemoryError(f"decide: candidate descriptor at step {step} has zero norm")
        delta = int(step) - kf.step
        insert, branch = should_insert(c, delta, self.conf)
        return insert, branch, c, delta

    def insert(self, kf: Keyframe) -> Keyframe | None:
        """Append ``kf``; returns the evicted oldest keyframe, if any."""
        if self._frames and kf.step <= self._frames[-1].step:
            raise KeyframeMemoryError(
                f"insert: keyframe step {kf.step} is not after the newest one ({self._frames[-1].step})")
        if self._frames and kf.descriptor.shape != self._frames[-1].descriptor.shape:
            raise KeyframeMemoryError(
                f"insert: descriptor length {kf.descriptor.size} differs from memory's "
                f"{self._frames[-1].descriptor.size}")
        self._frames.append(kf)
        if len(self._frames) > self.conf.capacity:
            return self._frames.popleft()
        return None

    def clear(self) -> None:
        self._frames.clear()
