"""What one synthetic encounter is made of before any pixel is drawn, and the poses it uses.

World frame: x east, y north, z up, metres; the ground is ``z = 0``. Cameras use
OpenCV axes; ``T_world_cam`` is camera-to-world. An :class:`EncounterPlan` holds
everything needed to render an encounter: static faces, moving objects with a
pose per step (other robots' bodies among them), every robot's camera
trajectory, intrinsics, stamps and the shading context.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..scene import CameraIntrinsics
from .renderer import FaceSet
from .textures import ShadeContext


@dataclass
class MovingObject:
    """Faces in the object frame and its pose ``T_world_obj [T,4,4]`` per step.
    ``owner`` is the robot index whose body this is (hidden from its own camera), or -1."""

    faces: FaceSet
    T_world_obj: np.ndarray
    owner: int = -1
    name: str = "object"


@dataclass
class EncounterPlan:
    """Everything needed to render one encounter (no pixels yet)."""

    name: str
    world: str
    static: FaceSet
    moving: list[MovingObject]
    robot_ids: list[str]
    T_world_cam: np.ndarray          # [N,T,4,4]
    intrinsics: CameraIntrinsics
    stamps_s: np.ndarray             # [T]
    ctx: ShadeContext
    meta: dict = field(default_factory=dict)

    @property
    def n_steps(self) -> int:
        return int(self.T_world_cam.shape[1])

    def faces_at(self, t: int, viewer: int | None = None) -> FaceSet:
        """World faces at step ``t``, without the body of robot ``viewer``."""
        parts = [self.static] + [m.faces.transformed(m.T_world_obj[t]) for m in self.moving
                                 if viewer is None or m.owner != viewer]
        return FaceSet.concat(parts)



def yaw_pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, z]
    return T


def camera_pose(x: float, y: float, z: float, yaw: float, pitch_down: float = 0.0) -> np.ndarray:
    """``T_world_cam`` of a camera at (x,y,z) looking along heading ``yaw``, tilted down by ``pitch_down``."""
    cp, sp = np.cos(pitch_down), np.sin(pitch_down)
    zc = np.array([cp * np.cos(yaw), cp * np.sin(yaw), -sp])
    xc = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    yc = np.cross(zc, xc)
    T = np.eye(4)
    T[:3, :3] = np.stack([xc, yc, zc], 1)
    T[:3, 3] = [x, y, z]
    return T
