"""Numpy to ROS 2 messages (``rosbags`` objects): what a bag written from a dataset, or a test
publisher, carries. The inverse of :mod:`cerpe.rosio.decode` (a round trip gives the same pixels,
depth to the stored unit, intrinsics and poses)."""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..geometry import se3_to_tq_xyzw
from ..scene import CameraIntrinsics
from .types import (CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, ODOMETRY, POSE_STAMPED, TF_MESSAGE, TRANSFORM_STAMPED,
                    RosInputError, msg_class)


def header(stamp_s: float, frame_id: str) -> Any:
    if not (np.isfinite(stamp_s) and 0 <= stamp_s < 2**31):
        raise RosInputError(f"stamp {stamp_s!r} s cannot be a ROS time (0 <= stamp < 2^31 s)")
    sec = int(np.floor(stamp_s))
    nanosec = min(int(round((stamp_s - sec) * 1e9)), 999_999_999)
    Time, Header = msg_class("builtin_interfaces/msg/Time"), msg_class("std_msgs/msg/Header")
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=str(frame_id))


def image(rgb: np.ndarray, stamp_s: float, frame_id: str, encoding: str = "rgb8") -> Any:
    """``[H,W,3] uint8`` RGB as a raw ``Image`` in ``rgb8``, ``bgr8`` or ``mono8`` (the channels' mean)."""
    img = np.asarray(rgb, dtype=np.uint8)
    if encoding == "bgr8":
        px = img[:, :, ::-1]
    elif encoding == "mono8":
        px = np.round(img.mean(axis=2)).astype(np.uint8)
    elif encoding == "rgb8":
        px = img
    else:
        raise RosInputError(f"cannot write an image as {encoding!r}; rgb8, bgr8 or mono8")
    px = np.ascontiguousarray(px)
    H, W = img.shape[:2]
    return msg_class(IMAGE)(header=header(stamp_s, frame_id), height=H, width=W, encoding=encoding,
                            is_bigendian=0, step=px.nbytes // H, data=px.reshape(-1).view(np.uint8))


def compressed(rgb: np.ndarray, stamp_s: float, frame_id: str, fmt: str = "jpeg", quality: int = 95) -> Any:
    """``[H,W,3] uint8`` RGB as a ``CompressedImage`` (``jpeg`` or ``png``)."""
    import cv2

    ext, flags = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, int(quality)]) if fmt == "jpeg" else (".png", [])
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(np.asarray(rgb)[:, :, ::-1]), flags)
    if not ok:
        raise RosInputError(f"{fmt} encoding failed")
    return msg_class(COMPRESSED_IMAGE)(header=header(stamp_s, frame_id), format=fmt,
                                       data=np.frombuffer(buf.tobytes(), np.uint8))


def depth(depth_m: np.ndarray, stamp_s: float, frame_id: str, encoding: str = "16UC1") -> Any:
    """``[H,W]`` metres as a depth ``Image``: ``16UC1`` (millimetres, rounded; 0 = none) or ``32FC1``."""
    d = np.asarray(depth_m, dtype=np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    if encoding == "16UC1":
        px = np.clip(np.round(d * 1000.0), 0, 65535).astype("<u2")
    elif encoding == "32FC1":
        px = d.astype("<f4")
    else:
        raise RosInputError(f"cannot write depth as {encoding!r}; 16UC1 or 32FC1")
    H, W = d.shape
    return msg_class(IMAGE)(header=header(stamp_s, frame_id), height=H, width=W, encoding=encoding,
                            is_bigendian=0, step=px.nbytes // H, data=np.ascontiguousarray(px).reshape(-1).view(np.uint8))


def camera_info(K: CameraIntrinsics, stamp_s: float, frame_id: str, dist: Sequence[float] = ()) -> Any:
    """Pinhole intrinsics (and OpenCV distortion) as a ``CameraInfo`` (``plumb_bob``)."""
    RoI = msg_class("sensor_msgs/msg/RegionOfInterest")
    k = np.array([K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1], dtype=np.float64)
    p = np.array([K.fx, 0, K.cx, 0, 0, K.fy, K.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    d = np.asarray(list(dist) or [0.0] * 5, dtype=np.float64)
    return msg_class(CAMERA_INFO)(header=header(stamp_s, frame_id), height=int(K.height), width=int(K.width),
                                  distortion_model="plumb_bob", d=d, k=k, r=np.eye(3).ravel(), p=p, binning_x=0,
                                  binning_y=0, roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def _pose(T: np.ndarray) -> Any:
    t, q = se3_to_tq_xyzw(np.asarray(T, dtype=np.float64))
    Point, Quat = msg_class("geometry_msgs/msg/Point"), msg_class("geometry_msgs/msg/Quaternion")
    return msg_class("geometry_msgs/msg/Pose")(position=Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                                               orientation=Quat(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                                w=float(q[3])))


def pose_stamped(T_parent_child: np.ndarray, stamp_s: float, frame_id: str) -> Any:
    return msg_class(POSE_STAMPED)(header=header(stamp_s, frame_id), pose=_pose(T_parent_child))


def transform(T_parent_child: np.ndarray, stamp_s: float, parent: str, child: str) -> Any:
    t, q = se3_to_tq_xyzw(np.asarray(T_parent_child, dtype=np.float64))
    V, Q = msg_class("geometry_msgs/msg/Vector3"), msg_class("geometry_msgs/msg/Quaternion")
    tf = msg_class("geometry_msgs/msg/Transform")(translation=V(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                                                  rotation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                             w=float(q[3])))
    return msg_class(TRANSFORM_STAMPED)(header=header(stamp_s, parent), child_frame_id=str(child), transform=tf)


def tf_message(transforms: Sequence[Any]) -> Any:
    return msg_class(TF_MESSAGE)(transforms=list(transforms))


def odometry(T_odom_base: np.ndarray, stamp_s: float, odom: str = "odom", base: str = "base_link") -> Any:
    """An ``Odometry`` with the pose only (twist and covariances zero)."""
    PwC = msg_class("geometry_msgs/msg/PoseWithCovariance")
    TwC, Twist, V = (msg_class("geometry_msgs/msg/TwistWithCovariance"), msg_class("geometry_msgs/msg/Twist"),
                     msg_class("geometry_msgs/msg/Vector3"))
    zero = V(x=0.0, y=0.0, z=0.0)
    return msg_class(ODOMETRY)(header=header(stamp_s, odom), child_frame_id=base,
                               pose=PwC(pose=_pose(T_odom_base), covariance=np.zeros(36)),
                               twist=TwC(twist=Twist(linear=zero, angular=zero), covariance=np.zeros(36)))
