"""A small TF buffer: static transforms (``/tf_static``) chained, one moving transform (``/tf``) by stamp.

What a robot's odometry needs from TF: the camera's pose on the robot, ``T_base_cam``, from the
static tree (``base_link -> camera_link -> camera_optical_frame``, any depth), and the robot's pose
``T_odom_base`` at an image's stamp from the dynamic ``odom -> base_link`` transforms. Frame ids are
compared without a leading ``/`` (ROS 1 bags often have one).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..stamped_poses import StampedPoses
from .decode import frames, pose, stamp_s


def strip(frame: str) -> str:
    return str(frame).lstrip("/")


class TfBuffer:
    """Static transforms by child frame; the moving ``parent -> child`` pair as a :class:`StampedPoses`."""

    def __init__(self, parent: str = "odom", child: str = "base_link", keep: int = 400) -> None:
        self.parent, self.child = strip(parent), strip(child)
        self.static: dict[str, tuple[str, np.ndarray]] = {}  # child -> (parent, T_parent_child)
        self.moving = StampedPoses(keep)

    def add_static(self, msg: Any, what: str) -> int:
        """Every transform of a ``TFMessage`` from ``/tf_static``; returns how many were kept."""
        n = 0
        for tf in msg.transforms:
            parent, child = frames(tf)
            self.static[child] = (parent, pose(tf, what))
            n += 1
        return n

    def add_dynamic(self, msg: Any, what: str) -> int:
        """The transforms of a ``TFMessage`` from ``/tf`` that are the moving pair (others ignored);
        returns how many were kept (a stamp not after the newest is not)."""
        n = 0
        for tf in msg.transforms:
            if frames(tf) == (self.parent, self.child):
                n += self.moving.add(stamp_s(tf), pose(tf, what))
        return n

    def static_T(self, parent: str, child: str) -> np.ndarray | None:
        """``T_parent_child`` through the static tree (child up to parent), None when they do not connect."""
        parent, child = strip(parent), strip(child)
        T = np.eye(4)
        frame, seen = child, set()
        while frame != parent:
            if frame in seen or frame not in self.static:
                return None
            seen.add(frame)
            up, T_up = self.static[frame]
            T = T_up @ T
            frame = up
        return T
