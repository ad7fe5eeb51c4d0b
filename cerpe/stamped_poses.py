"""A stream of poses by capture stamp, read at any stamp: interpolated, or extrapolated within a bound.

Robots running at their own pace need a pose at a stamp nobody sampled: a peer's odometry pose at
this robot's frame, the robot's own ``odom -> base_link`` at its image. :meth:`StampedPoses.at`
gives it between two samples at most ``max_gap_s`` apart (SLERP rotation, linear translation),
after the newest at the last velocity for at most ``max_extrapolation_s``, before the oldest held
for at most that long, and says which (``how``); beyond, nothing.

Pure numpy + :mod:`cerpe.geometry`; stamps are seconds in one clock (the caller maps others into it).
"""
from __future__ import annotations

import bisect

import numpy as np

from .geometry import interpolate_pose

#: two stamps this close (s) are one sample
SAME_STAMP_S = 1e-6

#: what :meth:`StampedPoses.at` did
HOW = ("exact", "interpolated", "extrapolated", "gap", "too-far", "none")


class StampedPoses:
    """The newest ``keep`` poses ``[4,4]`` of one stream, by increasing stamp (seconds); a stream that
    starts again (a restarted robot) is emptied by the caller (:meth:`clear`)."""

    def __init__(self, keep: int = 64) -> None:
        self.keep = int(keep)
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self.stamps)

    def clear(self) -> None:
        self.stamps, self.poses = [], []

    @property
    def newest_s(self) -> float | None:
        return self.stamps[-1] if self.stamps else None

    def add(self, stamp_s: float, T: np.ndarray) -> bool:
        """Keep ``T`` at ``stamp_s`` (in stamp order: poses may arrive out of order); False (not kept)
        when a pose of that stamp is kept already, or it is not finite. The oldest go beyond ``keep``."""
        s = float(stamp_s)
        T = np.asarray(T, dtype=np.float64)
        if not (np.isfinite(s) and np.all(np.isfinite(T))):
            return False
        k = bisect.bisect_left(self.stamps, s - SAME_STAMP_S)
        if k < len(self.stamps) and abs(self.stamps[k] - s) <= SAME_STAMP_S:
            return False
        self.stamps.insert(k, s)
        self.poses.insert(k, T.copy())
        if len(self.stamps) > self.keep:
            del self.stamps[0], self.poses[0]
        return True

    def at(self, stamp_s: float, max_gap_s: float, max_extrapolation_s: float) -> tuple[np.ndarray | None, str]:
        """``(pose at stamp_s or None, how)``, ``how`` one of :data:`HOW`:

        ``exact`` a sample there; ``interpolated`` between the two around it (at most ``max_gap_s``
        apart, else ``gap``); ``extrapolated`` after the newest by at most ``max_extrapolation_s`` at
        the velocity of the two newest (held when they are farther than ``max_gap_s`` apart or there
        is one), or before the oldest by at most that much (held); else ``too-far``; ``none`` when
        the stream is empty.
        """
        s = float(stamp_s)
        st = self.stamps
        if not st:
            return None, "none"
        k = bisect.bisect_left(st, s - SAME_STAMP_S)
        if k < len(st) and abs(st[k] - s) <= SAME_STAMP_S:
            return self.poses[k].copy(), "exact"
        if 0 < k < len(st):
            a, b = st[k - 1], st[k]
            if b - a > max_gap_s:
                return None, "gap"
            return interpolate_pose(self.poses[k - 1], self.poses[k], (s - a) / (b - a)), "interpolated"
        if k == 0:  # before the oldest: held
            return (self.poses[0].copy(), "extrapolated") if st[0] - s <= max_extrapolation_s else (None, "too-far")
        if s - st[-1] > max_extrapolation_s:
            return None, "too-far"
        if len(st) < 2 or st[-1] - st[-2] > max_gap_s:
            return self.poses[-1].copy(), "extrapolated"
        a, b = st[-2], st[-1]
        return interpolate_pose(self.poses[-2], self.poses[-1], (s - a) / (b - a)), "extrapolated"
