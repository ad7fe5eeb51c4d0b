"""Lazy image and depth references that transform what they read: undistort, resize, rotate.

An adapter that must change the pixels it hands to ``cerpe`` (TUM fr1/fr2 images
are distorted; pair lists resize and rotate) puts an :class:`ImageFile` or
:class:`DepthFile` into :class:`cerpe.scene.RobotStream` instead of a path. Both
are zero-argument callables (what ``cerpe.scene.load_rgb`` / ``load_depth_m``
accept) that keep the ``path`` they read, so ``cerpe check`` names the file.

Order of operations: read (the stored pixel grid: EXIF orientation is ignored,
intrinsics describe the stored grid) -> undistort -> resize -> rotate by
``rot90`` quarter turns counter-clockwise. :func:`transformed_intrinsics` gives
the intrinsics that match, and :func:`rot90_T` the camera rotation.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..scene import CameraIntrinsics, SceneError

ALPHA = 0.0  # cv2.getOptimalNewCameraMatrix: 0 keeps only valid pixels (no black border), 1 keeps every source pixel


@dataclass(frozen=True, eq=False)
class Undistortion:
    """Undistortion of one camera, its maps computed once.

    Attributes:
        K: the distorted camera's intrinsics.
        dist: OpenCV distortion coefficients ``k1 k2 p1 p2 [k3 ...]``.
        intrinsics: the pinhole intrinsics of the undistorted images (same size,
            ``cv2.getOptimalNewCameraMatrix`` with ``alpha`` = :data:`ALPHA`).
    """

    K: CameraIntrinsics
    dist: tuple[float, ...]
    intrinsics: CameraIntrinsics = field(init=False)
    _maps: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        import cv2

        size = (self.K.width, self.K.height)
        D = np.asarray(self.dist, dtype=np.float64)
        newK, _ = cv2.getOptimalNewCameraMatrix(self.K.K, D, size, ALPHA, size)
        maps = cv2.initUndistortRectifyMap(self.K.K, D, None, newK, size, cv2.CV_32FC1)
        new = CameraIntrinsics(fx=float(newK[0, 0]), fy=float(newK[1, 1]), cx=float(newK[0, 2]), cy=float(newK[1, 2]),
                               width=self.K.width, height=self.K.height)
        object.__setattr__(self, "intrinsics", new)
        object.__setattr__(self, "_maps", maps)

    def apply(self, img: np.ndarray, nearest: bool, what: str) -> np.ndarray:
        """Undistort an image (bilinear) or a depth map (``nearest``: never blends depth across edges)."""
        import cv2

        if img.shape[:2] != (self.K.height, self.K.width):
            raise SceneError(f"{what}: is {img.shape[1]}x{img.shape[0]}, the camera is {self.K.width}x{self.K.height}")
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(img, self._maps[0], self._maps[1], interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _read(path: Path, flags: int, what: str) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise SceneError(f"{what}: file not found: {path}")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise SceneError(f"{what}: cannot decode image file (corrupt or not an image): {path}")
    return img


def _resize_rotate(img: np.ndarray, size: tuple[int, int] | None, rot90: int, nearest: bool) -> np.ndarray:
    import cv2

    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)
    if rot90 % 4:
        img = np.ascontiguousarray(np.rot90(img, rot90 % 4))
    return img


@dataclass(frozen=True)
class ImageFile:
    """A colour image file read as ``[H,W,3] uint8`` RGB, then undistorted / resized / rotated."""

    path: Path
    undistort: Undistortion | None = None
    size: tuple[int, int] | None = None  # (width, height) after undistortion
    rot90: int = 0

    def __call__(self) -> np.ndarray:
        import cv2

        bgr = _read(Path(self.path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION, "image")
        if self.undistort is not None:
            bgr = self.undistort.apply(bgr, False, f"image {self.path}")
        return np.ascontiguousarray(_resize_rotate(bgr, self.size, self.rot90, False)[:, :, ::-1])


@dataclass(frozen=True)
class DepthFile:
    """An integer depth image read as ``[H,W] float32`` metres (0 = invalid), then transformed like its image.

    Attributes:
        units_per_m: stored value per metre (TUM: 5000; millimetres: 1000).
        invalid: stored values that mean "no measurement" besides 0 (7-Scenes: 65535).
    """

    path: Path
    units_per_m: float
    invalid: tuple[int, ...] = ()
    undistort: Undistortion | None = None
    size: tuple[int, int] | None = None
    rot90: int = 0

    def __call__(self) -> np.ndarray:
        import cv2

        raw = _read(Path(self.path), cv2.IMREAD_UNCHANGED, "depth")
        if raw.ndim != 2:
            raise SceneError(f"depth: expected a single-channel depth image, got shape {raw.shape}: {self.path}")
        if self.invalid:
            raw = np.where(np.isin(raw, self.invalid), 0, raw)
        if self.undistort is not None:
            raw = self.undistort.apply(raw, True, f"depth {self.path}")
        raw = _resize_rotate(raw, self.size, self.rot90, True)
        d = raw.astype(np.float32) / np.float32(self.units_per_m)
        return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)


def resized_intrinsics(K: CameraIntrinsics, size: tuple[int, int] | None) -> CameraIntrinsics:
    """Intrinsics of ``K``'s image resized to ``size = (width, height)`` (pixel-corner aligned)."""
    if size is None or (K.width, K.height) == tuple(size):
        return K
    return K.scaled(size[0] / K.width, size[1] / K.height)


def rot90_intrinsics(K: CameraIntrinsics, rot90: int) -> CameraIntrinsics:
    """Intrinsics after ``np.rot90(image, rot90)`` (quarter turns counter-clockwise).

    One turn maps pixel ``(u, v)`` of a ``W``-wide image to ``(v, W-1-u)``: the new
    camera has ``x' = y``, ``y' = -x`` (see :func:`rot90_T`).
    """
    for _ in range(rot90 % 4):
        K = CameraIntrinsics(fx=K.fy, fy=K.fx, cx=K.cy, cy=K.width - 1 - K.cx, width=K.height, height=K.width)
    return K


def rot90_T(rot90: int) -> np.ndarray:
    """``[4,4]`` ``T_rot_cam``: points of the original camera in the rotated one (``x' = y, y' = -x`` per turn)."""
    R1 = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.linalg.matrix_power(R1, rot90 % 4)
    return T


def transformed_intrinsics(K: CameraIntrinsics, undistort: Undistortion | None = None,
                           size: tuple[int, int] | None = None, rot90: int = 0) -> CameraIntrinsics:
    """The intrinsics of what :class:`ImageFile` returns with the same arguments."""
    if undistort is not None:
        K = undistort.intrinsics
    return rot90_intrinsics(resized_intrinsics(K, size), rot90)


def undistortion(K: CameraIntrinsics, dist: Sequence[float]) -> Undistortion | None:
    """An :class:`Undistortion` for non-zero ``dist``, None when the camera is already pinhole."""
    if not any(abs(float(d)) > 1e-12 for d in dist):
        return None
    return Undistortion(K, tuple(float(d) for d in dist))
