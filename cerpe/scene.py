"""The common in-memory form every dataset adapter produces and the algorithm consumes.

A *setting* (one column group of Table I) holds *encounters*; an encounter holds
2..N time-synchronised *robot streams* of equal length ``T``: step ``t`` of every
stream was captured at (nearly) the same time. Adapters do the synchronisation
and report the residual stamp differences.

Images and depth are referenced lazily (a path, an in-memory array or a
zero-argument callable) so a long sequence never sits in memory whole.
Ground-truth poses ``T_world_cam`` share one world frame across all robots of an
encounter; robots themselves never see it (it is for evaluation only).
"""
from __future__ import annotations

from .errors import CerpeError
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence, Union

import numpy as np

from .geometry import paper_T_ij, viewing_angle


class SceneError(CerpeError, ValueError):
    """Raised for inconsistent scene data; the message names the robot/frame/file."""


ImageRef = Union[Path, str, np.ndarray, Callable[[], np.ndarray]]
DepthRef = Union[Path, str, np.ndarray, Callable[[], np.ndarray], None]


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels, OpenCV convention (pixel centres at integers)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals) or self.fx <= 0 or self.fy <= 0:
            raise SceneError(f"intrinsics: fx, fy must be finite and > 0, got {vals}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise SceneError(f"intrinsics: image size must be positive, got {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """``[3,3]`` calibration matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled(self, sx: float, sy: float | None = None) -> "CameraIntrinsics":
        """Intrinsics of the image resized by ``sx`` (and ``sy``) with corner-aligned pixels."""
        sy = sx if sy is None else sy
        return CameraIntrinsics(
            fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
            width=int(round(self.width * sx)), height=int(round(self.height * sy)),
        )

    def as_list(self) -> list[float]:
        return [self.fx, self.fy, self.cx, self.cy, self.width, self.height]


def load_rgb(ref: ImageRef, what: str = "image") -> np.ndarray:
    """Resolve an :data:`ImageRef` to ``[H,W,3] uint8`` RGB, with errors naming ``what``."""
    if callable(ref) and not isinstance(ref, (str, Path)):
        img = ref()
    elif isinstance(ref, np.ndarray):
        img = ref
    else:
        import cv2

        path = Path(ref)
        if not path.is_file():
            raise SceneError(f"{what}: file not found: {path}")
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise SceneError(f"{what}: cannot decode image file (corrupt or not an image): {path}")
        img = bgr[:, :, ::-1]
    img = np.asarray(img)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4) or img.shape[0] == 0 or img.shape[1] == 0:
        raise SceneError(f"{what}: expected an HxWx3 image, got shape {img.shape}")
    if img.shape[2] == 4:
        img = img[:, :, :3]
    if img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.floating) and np.nanmax(img) <= 1.0 + 1e-6:
            img = np.clip(img * 255.0 + 0.5, 0, 255)
        img = np.clip(np.nan_to_num(img), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def load_depth_m(ref: DepthRef, units_per_m: float = 1.0, what: str = "depth") -> np.ndarray | None:
    """Resolve a :data:`DepthRef` to ``[H,W] float32`` metres; invalid pixels are 0.

    Files: 16-bit PNG (divided by ``units_per_m``, e.g. 5000 for TUM, 1000 for mm),
    ``.npy`` (already metres unless ``units_per_m`` says otherwise) or ``.exr``.
    Non-finite and non-positive values become 0 (= no measurement).
    """
    if ref is None:
        return None
    if callable(ref) and not isinstance(ref, (str, Path)):
        d = np.asarray(ref(), dtype=np.float32)
    elif isinstance(ref, np.ndarray):
        d = ref.astype(np.float32)
    else:
        path = Path(ref)
        if not path.is_file():
            raise SceneError(f"{what}: file not found: {path}")
        if path.suffix == ".npy":
            try:
                d = np.load(path).astype(np.float32)
            except Exception as exc:  # truncated / not an array
                raise SceneError(f"{what}: cannot read .npy depth {path}: {exc}") from None
        else:
            import cv2

            d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if d is None:
                raise SceneError(f"{what}: cannot decode depth image (corrupt or not an image): {path}")
            d = d.astype(np.float32)
        d = d / float(units_per_m)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    if d.ndim != 2 or d.size == 0:
        raise SceneError(f"{what}: expected an HxW depth map, got shape {d.shape}")
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    return d


@dataclass
class RobotStream:
    """One robot's synchronised frames inside an encounter.

    Attributes:
        robot_id: a short name (``"r0"``, ``"limo06"``, a nuScenes vehicle name).
        intrinsics: camera intrinsics (one camera per robot).
        stamps_s: ``[T]`` capture times in seconds.
        images: ``T`` image references (see :func:`load_rgb`).
        T_world_cam: ``[T,4,4]`` ground-truth camera-to-world poses in the
            encounter's shared world frame; rows of NaN where unknown.
        depth: optional ``T`` depth references (metric, from a sensor or a
            dataset), with ``depth_units_per_m`` for integer files.
        depth_units_per_m: divisor that turns stored depth values into metres.
        frame_ids: ``T`` stable identifiers (file stems, sample tokens) for logs.
    """

    robot_id: str
    intrinsics: CameraIntrinsics
    stamps_s: np.ndarray
    images: Sequence[ImageRef]
    T_world_cam: np.ndarray
    depth: Sequence[DepthRef] | None = None
    depth_units_per_m: float = 1.0
    frame_ids: Sequence[str] | None = None

    def __post_init__(self) -> None:
        self.stamps_s = np.asarray(self.stamps_s, dtype=np.float64)
        self.T_world_cam = np.asarray(self.T_world_cam, dtype=np.float64)
        T = len(self.stamps_s)
        if len(self.images) != T:
            raise SceneError(f"robot {self.robot_id}: {len(self.images)} images for {T} stamps")
        if self.T_world_cam.shape != (T, 4, 4):
            raise SceneError(f"robot {self.robot_id}: T_world_cam shape {self.T_world_cam.shape}, expected ({T},4,4)")
        if self.depth is not None and len(self.depth) != T:
            raise SceneError(f"robot {self.robot_id}: {len(self.depth)} depth maps for {T} stamps")
        if self.frame_ids is None:
            self.frame_ids = [f"{self.robot_id}:{t}" for t in range(T)]

    def __len__(self) -> int:
        return len(self.stamps_s)

    def image(self, t: int) -> np.ndarray:
        return load_rgb(self.images[t], what=f"robot {self.robot_id} frame {self.frame_ids[t]}")

    def depth_m(self, t: int) -> np.ndarray | None:
        if self.depth is None:
            return None
        return load_depth_m(self.depth[t], self.depth_units_per_m,
                            what=f"robot {self.robot_id} depth {self.frame_ids[t]}")

    def has_gt(self, t: int) -> bool:
        return bool(np.all(np.isfinite(self.T_world_cam[t])))


@dataclass
class Encounter:
    """2..N robots over ``T`` synchronised steps.

    Attributes:
        name: unique within its setting (used for run folders).
        robots: the streams, all of length ``T``.
        overlap: optional ``[T, N, N]`` ground-truth visual-overlap ratio: fraction
            of robot a's pixels at step t visible in robot b's image (a != b).
        meta: free-form provenance (generator seed, layout, source files).
    """

    name: str
    robots: list[RobotStream]
    overlap: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.robots) < 2:
            raise SceneError(f"encounter {self.name}: needs at least 2 robots, got {len(self.robots)}")
        lens = {len(r) for r in self.robots}
        if len(lens) != 1:
            raise SceneError(f"encounter {self.name}: robots have different lengths {sorted(lens)}")
        ids = [r.robot_id for r in self.robots]
        if len(set(ids)) != len(ids):
            raise SceneError(f"encounter {self.name}: duplicate robot ids {ids}")
        if self.overlap is not None:
            self.overlap = np.asarray(self.overlap, dtype=np.float64)
            n = len(self.robots)
            if self.overlap.shape != (self.n_steps, n, n):
                raise SceneError(f"encounter {self.name}: overlap shape {self.overlap.shape}, expected ({self.n_steps},{n},{n})")

    @property
    def n_steps(self) -> int:
        return len(self.robots[0])

    @property
    def robot_ids(self) -> list[str]:
        return [r.robot_id for r in self.robots]

    def ordered_pairs(self) -> list[tuple[int, int]]:
        """Every ordered pair ``(i, j)``, i != j. Robot i (the ego robot) estimates
        the paper's ``T_ij`` = ``T_cj_ci`` (pose of its own camera seen from j's)."""
        n = len(self.robots)
        return [(i, j) for i in range(n) for j in range(n) if i != j]

    def gt_T_cj_ci(self, t: int, i: int, j: int) -> np.ndarray | None:
        """Ground-truth ``T_ij`` (= ``T_cj_ci``) at step ``t``, or None when unknown."""
        a, b = self.robots[i], self.robots[j]
        if not (a.has_gt(t) and b.has_gt(t)):
            return None
        return paper_T_ij(a.T_world_cam[t], b.T_world_cam[t])

    def gt_viewing_angle(self, t: int, i: int, j: int) -> float:
        T = self.gt_T_cj_ci(t, i, j)
        return float("nan") if T is None else float(viewing_angle(T))


@dataclass
class Setting:
    """One column group of Table I: a named set of encounters and how to evaluate it."""

    name: str
    encounters: list[Encounter]
    metric_depth: str = "dataset"
    meta: dict = field(default_factory=dict)
    metric_depth_options: dict = field(default_factory=dict)  # keyword options of the depth source
