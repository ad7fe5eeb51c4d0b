"""A peer's odometry poses as one robot saw them, and the bridge over a missing one (message loss).

A robot learns robot j's odometry pose ``X_j^t`` (``T_odom_cam``) from j's pose
message of step t and, since messages version 2, from j's image replies (the pose
j had when it answered: of step t when it had one, else of step t-1). When the pose
message of step t is lost, :meth:`PoseLog.bridged` estimates ``X_j^t`` from what
was seen: between two known poses it interpolates (SLERP rotation, linear
translation), after the newest one it extrapolates at the last constant velocity
(holds with a single pose). An anchor stored with a bridged pose is corrected when a
later pose arrives (:meth:`PoseLog.note` interpolates it then), so the pair keeps a
usable anchor although that message never came.

Pure numpy + :mod:`cerpe.geometry`; no link or record here.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from ..geometry import interpolate_pose


class _HasXj(Protocol):
    X_j: np.ndarray


class PoseLog:
    """The newest ``keep`` poses seen of one peer, by step, and the anchors waiting for a bridge.

    Args:
        keep: poses kept (older ones are forgotten; a bridge needs the two around a step).
    """

    def __init__(self, keep: int = 8) -> None:
        self.keep = int(keep)
        self._poses: dict[int, np.ndarray] = {}
        self._pending: list[tuple[int, _HasXj]] = []

    def note(self, step: int, X: np.ndarray) -> int:
        """Remember ``X`` of ``step``; returns how many waiting anchors it corrected (interpolated now)."""
        step = int(step)
        if step in self._poses:
            return 0
        self._poses[step] = np.array(X, dtype=np.float64)
        for old in sorted(self._poses)[:-self.keep]:
            del self._poses[old]
        fixed, still = 0, []
        for t, anchor in self._pending:
            if t < step:
                X_t = self.bridged(t)
                if X_t is not None:
                    anchor.X_j = X_t
                    fixed += 1
            else:
                still.append((t, anchor))
        self._pending = still
        return fixed

    def exact(self, step: int) -> np.ndarray | None:
        """The pose of ``step`` when it was seen."""
        X = self._poses.get(int(step))
        return None if X is None else X.copy()

    def bridged(self, step: int) -> np.ndarray | None:
        """``X^step``: seen, else interpolated between the poses around it, else extrapolated from the
        two newest before it at constant velocity (held with one); None when none before or after."""
        step = int(step)
        if step in self._poses:
            return self._poses[step].copy()
        before = [s for s in self._poses if s < step]
        after = [s for s in self._poses if s > step]
        if before and after:
            a, b = max(before), min(after)
            return interpolate_pose(self._poses[a], self._poses[b], (step - a) / (b - a))
        if not before:
            return self._poses[min(after)].copy() if after else None
        b = max(before)
        older = [s for s in before if s < b]
        if not older:
            return self._poses[b].copy()
        a = max(older)
        return interpolate_pose(self._poses[a], self._poses[b], (step - a) / (b - a))

    def defer(self, step: int, anchor: _HasXj) -> None:
        """``anchor`` (measured at ``step``) carries a bridged ``X_j``: correct it when a later pose comes."""
        self._pending.append((int(step), anchor))
