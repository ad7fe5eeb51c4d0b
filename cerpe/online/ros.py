"""ROS 2 on Zenoh without ROS: the keys of ROS topics, rmw_zenoh's attachment, the CDR of an estimate.

Two key layouts, the ones a ROS 2 graph reaches Zenoh by: ``rmw_zenoh`` (``<domain>/<topic>/<DDS
type name>/<type hash>``, each sample with rmw_zenoh's 33-byte attachment) and ``ros2dds`` (the key
``zenoh-bridge-ros2dds`` maps a DDS topic to: the topic without its leading ``/``, bare CDR). An
estimate is a ``geometry_msgs/msg/PoseWithCovarianceStamped`` on
``/cerpe/<team>/<i>/relative_pose/<j>``: pose ``T_cj_ci`` (camera ``i`` in camera ``j``, optical
axes, metres), frame id ``<team>/<j>/camera_optical``, stamp = capture time, covariance in ROS order
(``x y z rot_x rot_y rot_z`` in the parent frame; all zeros only when unknown). The keys and bytes
are described once, in ``docs/online.md``; this module builds and parses them.
"""
from __future__ import annotations

import re
import struct
from typing import Any, Mapping

import numpy as np

from ..errors import CerpeError
from ..geometry import GeometryError, check_se3, pose_cov_in_parent, se3_from_tq_xyzw
from ..rosio import encode as rencode
from ..rosio import types as rt

ROS_TYPE = rt.POSE_COV_STAMPED
DDS_TYPE = rt.dds_type_name(ROS_TYPE)
HUMBLE_HASH = "TypeHashNotSupported"
KEY_FORMATS = ("rmw_zenoh", "ros2dds")

DISTROS = ("humble", "jazzy", "kilted", "rolling")  # the ROS 2 distributions rmw_zenoh is released for

default_conf: dict[str, Any] = {
    "domain_id": 0,            # ROS_DOMAIN_ID of the graph that reads the estimates
    "distro": "jazzy",         # one of DISTROS: "humble" (no type hashes) or a later one
    "key_format": "rmw_zenoh",  # or "ros2dds" (through zenoh-bridge-ros2dds)
}

#: the variance a published covariance gives what is not known (the translation without metric depth)
UNKNOWN_VAR = 100.0**2

_TOKEN = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_ATTACHMENT = struct.Struct("<qqB16s")


class RosError(CerpeError, ValueError):
    """A name that cannot be a ROS topic token, a bad pose or covariance, a bad option."""


def check_distro(distro: Any) -> str:
    """``distro`` when it is one of :data:`DISTROS`; a :class:`RosError` listing them otherwise (an
    older distribution would silently get a later one's keys)."""
    if str(distro).lower() not in DISTROS:
        raise RosError(f"--ros-distro {distro!r}: not supported; supported: {', '.join(DISTROS)}")
    return str(distro).lower()


def type_hash(distro: str, msgtype: str = ROS_TYPE) -> str:
    """rmw_zenoh's type-hash key chunk for ``msgtype`` under ``distro`` (one of :data:`DISTROS`)."""
    return HUMBLE_HASH if check_distro(distro) == "humble" else rt.type_hash(msgtype)


def ros_token(name: str, what: str) -> str:
    if not _TOKEN.match(str(name)):
        raise RosError(f"{what} {name!r}: not a ROS name token (a letter, then letters, digits or '_'); "
                       f"ROS 2 topics are named after it")
    return str(name)


def topic_name(team: str, ego: str, other: str) -> str:
    """``/cerpe/<team>/<ego>/relative_pose/<other>``."""
    return (f"/cerpe/{ros_token(team, '--team')}/{ros_token(ego, 'robot id')}/relative_pose/"
            f"{ros_token(other, 'robot id')}")


def camera_frame_id(team: str, robot: str) -> str:
    return f"{team}/{robot}/camera_optical"


def peer_frame_id(team: str, ego: str, other: str) -> str:
    """TF frame of ``other``'s camera as ``ego`` places it (a child of ``ego``'s camera frame): each robot
    publishes its own, so two robots' estimates never give one frame two parents."""
    return f"{team}/{ego}/peers/{other}/camera_optical"


def zenoh_key(topic: str, conf: Mapping[str, Any], msgtype: str = ROS_TYPE) -> str:
    """The Zenoh key of ``topic`` carrying ``msgtype`` for ``conf`` (see the module docstring)."""
    if conf["key_format"] == "ros2dds":
        return topic.strip("/")
    return f"{int(conf['domain_id'])}/{topic.strip('/')}/{rt.dds_type_name(msgtype)}/{type_hash(conf['distro'], msgtype)}"


def subscription_key(topic: str, conf: Mapping[str, Any]) -> str:
    """What subscribes to ``topic`` of any type: rmw_zenoh's key with the type and hash chunks left open."""
    if conf["key_format"] == "ros2dds":
        return topic.strip("/")
    return f"{int(conf['domain_id'])}/{topic.strip('/')}/*/*"


def key_type(key: str, conf: Mapping[str, Any]) -> str | None:
    """The message type an rmw_zenoh key names (``pkg/msg/Name``); None for ros2dds keys (they name none)."""
    if conf["key_format"] == "ros2dds":
        return None
    parts = str(key).split("/")
    return rt.ros_type_name(parts[-2]) if len(parts) >= 4 else None


def rmw_attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's per-sample attachment (33 bytes)."""
    if len(gid) != 16:
        raise RosError(f"publisher GID must be 16 bytes, got {len(gid)}")
    return _ATTACHMENT.pack(int(sequence), int(stamp_ns), 16, bytes(gid))


def parse_rmw_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(sequence, stamp_ns, gid)`` of an rmw_zenoh attachment."""
    if len(data) != _ATTACHMENT.size:
        raise RosError(f"rmw_zenoh attachment must be {_ATTACHMENT.size} bytes, got {len(data)}")
    seq, stamp_ns, n, gid = _ATTACHMENT.unpack(data)
    if n != 16:
        raise RosError(f"rmw_zenoh attachment: GID length {n}, expected 16")
    return seq, stamp_ns, gid


def ros_covariance(T_cj_ci: np.ndarray, cov: Any) -> np.ndarray:
    """A right-perturbation covariance ``[rotation, translation]`` of ``T_cj_ci`` (``PairRecord.cov``) in ROS
    order and frame (:func:`~cerpe.geometry.pose_cov_in_parent`); a block of NaN (not known: no metric
    depth) gets :data:`UNKNOWN_VAR` on its diagonal and no correlation. None: all zeros (unknown)."""
    if cov is None:
        return np.zeros((6, 6))
    C = np.array(cov, dtype=np.float64)
    for blk in (slice(0, 3), slice(3, 6)):
        if not np.all(np.isfinite(C[blk, blk])):
            C[blk, :] = 0.0
            C[:, blk] = 0.0
            C[blk, blk] = np.eye(3) * UNKNOWN_VAR
    C[~np.isfinite(C)] = 0.0
    return pose_cov_in_parent(T_cj_ci, 0.5 * (C + C.T))


def _covariance(cov: Any) -> np.ndarray:
    if cov is None:
        return np.zeros(36)  # ROS: all zeros = covariance unknown
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)) or not np.allclose(c, c.T, atol=1e-12, rtol=1e-9):
        raise RosError(f"covariance must be a finite symmetric 6x6 matrix (x y z rot_x rot_y rot_z), "
                       f"got shape {c.shape}")
    if np.any(np.diag(c) < 0):
        raise RosError("covariance has a negative variance on its diagonal")
    return c.ravel()


def _check(T: Any, stamp_s: float, what: str) -> np.ndarray:
    try:
        T = check_se3(T, what)
    except GeometryError as exc:
        raise RosError(f"pose to publish: {exc}") from None
    stamp = float(stamp_s)
    if not (np.isfinite(stamp) and 0 <= stamp < 2**31):
        raise RosError(f"stamp {stamp_s!r} s cannot be a ROS time (0 <= stamp < 2^31 s)")
    return T


def encode_pose_cdr(T_cj_ci: Any, stamp_s: float, frame_id: str, covariance: Any = None) -> bytes:
    """One ``PoseWithCovarianceStamped`` as CDR (little endian, with its 4-byte encapsulation header);
    ``covariance``: 6x6 in ROS order (None: all zeros, unknown)."""
    T = _check(T_cj_ci, stamp_s, "T_cj_ci")
    cov = _covariance(covariance)
    PwC = rt.msg_class("geometry_msgs/msg/PoseWithCovariance")
    pose = rencode.pose_stamped(T, float(stamp_s), frame_id).pose
    msg = rt.msg_class(ROS_TYPE)(header=rencode.header(float(stamp_s), frame_id), pose=PwC(pose=pose, covariance=cov))
    return rt.serialize(msg, ROS_TYPE)


def decode_pose_cdr(data: bytes) -> dict[str, Any]:
    """``{"T_cj_ci", "stamp_s", "frame_id", "covariance" (6x6)}`` of a CDR ``PoseWithCovarianceStamped``."""
    try:
        m = rt.typestore().deserialize_cdr(bytes(data), ROS_TYPE)
    except Exception as exc:  # rosbags raises several types for truncated or foreign data
        raise RosError(f"not a CDR {ROS_TYPE}: {exc}") from None
    p, o = m.pose.pose.position, m.pose.pose.orientation
    return {"T_cj_ci": se3_from_tq_xyzw([p.x, p.y, p.z], [o.x, o.y, o.z, o.w]),
            "stamp_s": m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
            "frame_id": m.header.frame_id, "covariance": np.asarray(m.pose.covariance, np.float64).reshape(6, 6)}


def encode_tf_cdr(transforms: list[tuple[np.ndarray, float, str, str]]) -> bytes:
    """A ``tf2_msgs/msg/TFMessage`` of ``(T_parent_child, stamp_s, parent, child)`` as CDR."""
    msgs = [rencode.transform(_check(T, s, "transform"), float(s), parent, child) for T, s, parent, child in transforms]
    return rt.serialize(rencode.tf_message(msgs), rt.TF_MESSAGE)
