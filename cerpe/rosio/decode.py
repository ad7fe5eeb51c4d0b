"""ROS messages (``rosbags`` objects, ROS 1 or ROS 2) to what the algorithm takes.

Each function raises one :class:`~cerpe.rosio.types.RosInputError` naming ``what`` (a topic or a bag
field) and the message field at fault; a live robot counts it and drops the message, an adapter lists it.

* colour: ``sensor_msgs/Image`` in ``rgb8``, ``bgr8``, ``mono8``, ``rgba8``, ``bgra8`` (any row
  padding), or a ``CompressedImage`` OpenCV decodes (JPEG, PNG) -> ``[H,W,3] uint8`` RGB;
* depth: ``Image`` ``16UC1``/``mono16`` (millimetres) or ``32FC1`` (metres) -> ``[H,W] float32``
  metres, 0 where there is no measurement (0, NaN, inf, negative);
* ``CameraInfo`` -> pinhole :class:`~cerpe.scene.CameraIntrinsics` and OpenCV distortion
  (``plumb_bob``, ``rational_polynomial``; other models are refused);
* ``Odometry``, ``PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped`` -> ``[4,4]``
  ``T_parent_child`` (``header.frame_id`` <- ``child_frame_id``; NaN refused).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..geometry import GeometryError, se3_from_tq_xyzw
from ..scene import CameraIntrinsics, SceneError
from .types import COMPRESSED_IMAGE, IMAGE, ODOMETRY, POSE_COV_STAMPED, POSE_STAMPED, TRANSFORM_STAMPED
from .types import RosInputError

#: colour encodings of ``sensor_msgs/Image`` read here -> (channels, order of the channels)
COLOUR_ENCODINGS: dict[str, tuple[int, str]] = {"rgb8": (3, "rgb"), "bgr8": (3, "bgr"), "mono8": (1, "mono"),
                                                "rgba8": (4, "rgb"), "bgra8": (4, "bgr")}
#: depth encodings -> (numpy dtype, metres per stored unit)
DEPTH_ENCODINGS: dict[str, tuple[str, float]] = {"16UC1": ("u2", 1e-3), "mono16": ("u2", 1e-3),
                                                 "32FC1": ("f4", 1.0)}
DISTORTION_MODELS: tuple[str, ...] = ("plumb_bob", "rational_polynomial", "")


def msgtype(msg: Any) -> str:
    return str(getattr(msg, "__msgtype__", type(msg).__name__))


def stamp_s(msg: Any) -> float:
    """``header.stamp`` in seconds."""
    st = msg.header.stamp
    return float(st.sec) + float(st.nanosec) * 1e-9


def _pixels(msg: Any, what: str, itemsize: int, channels: int) -> np.ndarray:
    """The rows of a raw ``Image`` without their padding, as ``[H, W*channels*itemsize]`` bytes."""
    H, W, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    row = W * channels * itemsize
    if H <= 0 or W <= 0:
        raise RosInputError(f"{what}: image of {W}x{H} pixels")
    if step < row or data.size < step * H:
        raise RosInputError(f"{what}: image data of {data.size} bytes (step {step}) does not hold {H} rows of "
                            f"{W} {msg.encoding} pixels")
    return data[: step * H].reshape(H, step)[:, :row]


def _raw_rgb(msg: Any, what: str) -> np.ndarray:
    enc = str(msg.encoding)
    if enc not in COLOUR_ENCODINGS:
        raise RosInputError(f"{what}: image encoding {enc!r} is not supported; supported: "
                            f"{', '.join(COLOUR_ENCODINGS)} (or a CompressedImage)")
    ch, order = COLOUR_ENCODINGS[enc]
    px = _pixels(msg, what, 1, ch).reshape(int(msg.height), int(msg.width), ch)
    if ch == 1:
        return np.repeat(px, 3, axis=2)
    px = px[:, :, :3]
    return np.ascontiguousarray(px[:, :, ::-1] if order == "bgr" else px)


def _compressed_rgb(msg: Any, what: str) -> np.ndarray:
    import cv2

    data = np.asarray(msg.data, dtype=np.uint8)
    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower().replace(" ", ""):
        raise RosInputError(f"{what}: a compressedDepth image on the colour topic (format {fmt!r})")
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise RosInputError(f"{what}: CompressedImage of format {fmt!r} ({data.size} bytes) does not decode")
    return np.ascontiguousarray(img[:, :, ::-1])


def image_rgb(msg: Any, what: str) -> np.ndarray:
    """An ``Image`` or ``CompressedImage`` as ``[H,W,3] uint8`` RGB."""
    kind = msgtype(msg)
    if kind == IMAGE:
        return _raw_rgb(msg, what)
    if kind == COMPRESSED_IMAGE:
        return _compressed_rgb(msg, what)
    raise RosInputError(f"{what}: a {kind} message where an image ({IMAGE} or {COMPRESSED_IMAGE}) was expected")


def depth_m(msg: Any, what: str) -> np.ndarray:
    """A depth ``Image`` as ``[H,W] float32`` metres (0: no measurement)."""
    if msgtype(msg) != IMAGE:
        raise RosInputError(f"{what}: a {msgtype(msg)} message where a depth {IMAGE} was expected")
    enc = str(msg.encoding)
    if enc not in DEPTH_ENCODINGS:
        raise RosInputError(f"{what}: depth encoding {enc!r} is not supported; supported: 16UC1 (mm), mono16 (mm), "
                            f"32FC1 (m)")
    code, unit = DEPTH_ENCODINGS[enc]
    size = np.dtype(code).itemsize
    px = _pixels(msg, what, size, 1)
    endian = ">" if int(msg.is_bigendian) else "<"
    d = np.ascontiguousarray(px).view(np.dtype(endian + code)).reshape(int(msg.height), int(msg.width))
    d = d.astype(np.float32) * np.float32(unit)
    return np.where(np.isfinite(d) & (d > 0), d, np.float32(0.0)).astype(np.float32)


def camera(msg: Any, what: str) -> tuple[CameraIntrinsics, tuple[float, ...]]:
    """A ``CameraInfo`` as ``(intrinsics of the image it describes, OpenCV distortion k1 k2 p1 p2 [k3 ...])``."""
    K = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), dtype=np.float64).ravel()
    D = np.asarray(getattr(msg, "d", getattr(msg, "D", ())), dtype=np.float64).ravel()
    W, H = int(msg.width), int(msg.height)
    model = str(msg.distortion_model)
    if K.size != 9 or not np.all(np.isfinite(K)):
        raise RosInputError(f"{what}: CameraInfo k must be 9 finite numbers, got {K.tolist()}")
    fx, fy, cx, cy = K[0], K[4], K[2], K[5]
    if W <= 0 or H <= 0:
        raise RosInputError(f"{what}: CameraInfo width x height is {W}x{H} (uncalibrated camera?)")
    if not (fx > 0 and fy > 0):
        raise RosInputError(f"{what}: CameraInfo k has fx={fx:g}, fy={fy:g} (uncalibrated camera: zeros?)")
    if not (0 <= cx < W and 0 <= cy < H):
        raise RosInputError(f"{what}: CameraInfo principal point ({cx:g}, {cy:g}) lies outside the {W}x{H} image")
    if model not in DISTORTION_MODELS:
        raise RosInputError(f"{what}: CameraInfo distortion_model {model!r} is not supported; supported: "
                            f"plumb_bob, rational_polynomial")
    if not np.all(np.isfinite(D)) or D.size not in (0, 4, 5, 8, 12, 14):
        raise RosInputError(f"{what}: CameraInfo d must be 0, 4, 5, 8, 12 or 14 finite numbers, got {D.tolist()}")
    bx, by = int(getattr(msg, "binning_x", 0) or 0), int(getattr(msg, "binning_y", 0) or 0)
    if bx > 1 or by > 1:
        raise RosInputError(f"{what}: CameraInfo binning {bx}x{by} is not supported (publish unbinned images)")
    try:
        K_ = CameraIntrinsics(fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), width=W, height=H)
    except SceneError as exc:
        raise RosInputError(f"{what}: {exc}") from None
    return K_, tuple(float(v) for v in D)


def pose(msg: Any, what: str) -> np.ndarray:
    """``[4,4]`` ``T_parent_child`` of an ``Odometry``, ``PoseStamped``, ``PoseWithCovarianceStamped`` or
    ``TransformStamped`` (parent ``header.frame_id``)."""
    kind = msgtype(msg)
    if kind == ODOMETRY or kind == POSE_COV_STAMPED:
        p = msg.pose.pose
        t, q = p.position, p.orientation
    elif kind == POSE_STAMPED:
        t, q = msg.pose.position, msg.pose.orientation
    elif kind == TRANSFORM_STAMPED:
        t, q = msg.transform.translation, msg.transform.rotation
    else:
        raise RosInputError(f"{what}: a {kind} message where a pose ({ODOMETRY}, {POSE_STAMPED}, "
                            f"{POSE_COV_STAMPED} or {TRANSFORM_STAMPED}) was expected")
    tv = np.array([t.x, t.y, t.z], dtype=np.float64)
    qv = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    if not (np.all(np.isfinite(tv)) and np.all(np.isfinite(qv))):
        raise RosInputError(f"{what}: {kind} pose holds NaN or inf (position {tv.tolist()}, orientation "
                            f"{qv.tolist()})")
    try:
        return se3_from_tq_xyzw(tv, qv)
    except GeometryError as exc:
        raise RosInputError(f"{what}: {kind} orientation {qv.tolist()}: {exc}") from None


def frames(msg: Any) -> tuple[str, str]:
    """``(parent, child)`` frame ids of a pose message (child "" where the type has none)."""
    return str(msg.header.frame_id).lstrip("/"), str(getattr(msg, "child_frame_id", "")).lstrip("/")
