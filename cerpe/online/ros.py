"""Estimates out to ROS 2: each robot's relative poses as ``geometry_msgs/msg/PoseWithCovarianceStamped``.

Topic ``/cerpe/<team>/<i>/relative_pose/<j>``, pose ``T_cj_ci`` (camera ``i`` in camera
``j``, optical axes, metres), frame id ``<team>/<j>/camera_optical``, stamp = capture
time, covariance all zeros when unknown (the ROS convention). CDR-encoded with
``rosbags`` and put on rmw_zenoh's data key (with its 33-byte attachment) or on the
key ``zenoh-bridge-ros2dds`` uses. The keys and bytes are described once, in
``docs/online.md``, "Wire format"; this module builds them.
No liveliness tokens are declared, so ``ros2 topic list`` does not show the topic; name
the type: ``ros2 topic echo /cerpe/lab/r0/relative_pose/r1 geometry_msgs/msg/PoseWithCovarianceStamped``.
"""
from __future__ import annotations

import functools
import os
import re
import struct
import time
from typing import Any, Iterable, Mapping

import numpy as np

from ..config import merge_conf
from ..errors import CerpeError
from ..geometry import GeometryError, check_se3, se3_from_tq_xyzw, se3_to_tq_xyzw

ROS_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
DDS_TYPE = "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
HUMBLE_HASH = "TypeHashNotSupported"
KEY_FORMATS = ("rmw_zenoh", "ros2dds")

DISTROS = ("humble", "jazzy", "kilted", "rolling")  # the ROS 2 distributions rmw_zenoh is released for

default_conf: dict[str, Any] = {
    "domain_id": 0,            # ROS_DOMAIN_ID of the graph that reads the estimates
    "distro": "jazzy",         # one of DISTROS: "humble" (no type hashes) or a later one
    "key_format": "rmw_zenoh",  # or "ros2dds" (through zenoh-bridge-ros2dds)
}

_TOKEN = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_ATTACHMENT = struct.Struct("<qqB16s")


class RosError(CerpeError, ValueError):
    """A name that cannot be a ROS topic token, a bad pose or covariance, a bad option."""


@functools.lru_cache(maxsize=1)
def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)  # PoseWithCovarianceStamped is the same in every ROS 2 distro


def check_distro(distro: Any) -> str:
    """``distro`` when it is one of :data:`DISTROS`; a :class:`RosError` listing them otherwise (an
    older distribution would silently get a later one's keys)."""
    if str(distro).lower() not in DISTROS:
        raise RosError(f"--ros-distro {distro!r}: not supported; supported: {', '.join(DISTROS)}")
    return str(distro).lower()


def type_hash(distro: str) -> str:
    """rmw_zenoh's type-hash key chunk for :data:`ROS_TYPE` under ``distro`` (one of :data:`DISTROS`)."""
    return HUMBLE_HASH if check_distro(distro) == "humble" else _typestore().hash_rihs01(ROS_TYPE)


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


def zenoh_key(topic: str, conf: Mapping[str, Any]) -> str:
    """The Zenoh key of ``topic`` for ``conf`` (see the module docstring)."""
    if conf["key_format"] == "ros2dds":
        return topic.lstrip("/")
    return f"{int(conf['domain_id'])}/{topic.lstrip('/')}/{DDS_TYPE}/{type_hash(conf['distro'])}"


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


def encode_pose_cdr(T_cj_ci: Any, stamp_s: float, frame_id: str, covariance: Any = None) -> bytes:
    """One ``PoseWithCovarianceStamped`` as CDR (little endian, with its 4-byte encapsulation header)."""
    types = _typestore().types
    Time, Header = types["builtin_interfaces/msg/Time"], types["std_msgs/msg/Header"]
    Point, Quaternion = types["geometry_msgs/msg/Point"], types["geometry_msgs/msg/Quaternion"]
    Pose, PoseWithCovariance = types["geometry_msgs/msg/Pose"], types["geometry_msgs/msg/PoseWithCovariance"]
    try:
        t, q = se3_to_tq_xyzw(check_se3(T_cj_ci, "T_cj_ci"))
    except GeometryError as exc:
        raise RosError(f"pose to publish: {exc}") from None
    stamp = float(stamp_s)
    if not (np.isfinite(stamp) and 0 <= stamp < 2**31):
        raise RosError(f"stamp {stamp_s!r} s cannot be a ROS time (0 <= stamp < 2^31 s)")
    sec = int(np.floor(stamp))
    nanosec = min(int(round((stamp - sec) * 1e9)), 999_999_999)
    msg = types[ROS_TYPE](header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=str(frame_id)),
                  pose=PoseWithCovariance(pose=Pose(position=Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                                                    orientation=Quaternion(x=float(q[0]), y=float(q[1]),
                                                                           z=float(q[2]), w=float(q[3]))),
                                          covariance=_covariance(covariance)))
    return bytes(_typestore().serialize_cdr(msg, ROS_TYPE))


def decode_pose_cdr(data: bytes) -> dict[str, Any]:
    """``{"T_cj_ci", "stamp_s", "frame_id", "covariance" (6x6)}`` of a CDR ``PoseWithCovarianceStamped``."""
    try:
        m = _typestore().deserialize_cdr(bytes(data), ROS_TYPE)
    except Exception as exc:  # rosbags raises several types for truncated or foreign data
        raise RosError(f"not a CDR {ROS_TYPE}: {exc}") from None
    p, o = m.pose.pose.position, m.pose.pose.orientation
    return {"T_cj_ci": se3_from_tq_xyzw([p.x, p.y, p.z], [o.x, o.y, o.z, o.w]),
            "stamp_s": m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
            "frame_id": m.header.frame_id, "covariance": np.asarray(m.pose.covariance, np.float64).reshape(6, 6)}


class EstimatePublisher:
    """Publishes one robot's relative-pose estimates on a Zenoh session (e.g. ``ZenohLink.session``).

    Args:
        session: an open ``zenoh.Session``.
        team, robot_id: this robot's team and id (ROS name tokens).
        conf: overrides of :data:`default_conf`.
    """

    def __init__(self, session: Any, team: str, robot_id: str, conf: Mapping[str, Any] | None = None) -> None:
        self.conf = merge_conf(default_conf, conf, "ros estimates conf")
        if self.conf["key_format"] not in KEY_FORMATS:
            raise RosError(f"ros key_format {self.conf['key_format']!r}: expected one of {KEY_FORMATS}")
        domain = self.conf["domain_id"]
        if not (isinstance(domain, int) and 0 <= domain <= 232):
            raise RosError(f"ros domain_id {domain!r}: expected an integer in 0..232 (ROS_DOMAIN_ID)")
        check_distro(self.conf["distro"])
        self.session, self.team, self.robot_id = session, ros_token(team, "--team"), ros_token(robot_id, "robot id")
        self.gid = os.urandom(16)
        self._pubs: dict[str, Any] = {}
        self._seq: dict[str, int] = {}

    def key(self, other: str) -> str:
        return zenoh_key(topic_name(self.team, self.robot_id, other), self.conf)

    def publish(self, other: str, T_cj_ci: Any, stamp_s: float, covariance: Any = None) -> int:
        """Publish this robot's estimate of ``T_cj_ci`` (j = ``other``); returns the CDR bytes."""
        cdr = encode_pose_cdr(T_cj_ci, stamp_s, camera_frame_id(self.team, other), covariance)
        if other not in self._pubs:
            self._pubs[other] = self.session.declare_publisher(self.key(other))
            self._seq[other] = 0
        self._seq[other] += 1
        if self.conf["key_format"] == "rmw_zenoh":
            self._pubs[other].put(cdr, attachment=rmw_attachment(self._seq[other], time.time_ns(), self.gid))
        else:
            self._pubs[other].put(cdr)
        return len(cdr)

    def publish_pairs(self, pairs: Iterable[Any]) -> int:
        """Publish every :class:`~cerpe.records.PairRecord` of this robot that has an estimate."""
        n = 0
        for rec in pairs:
            if rec.ego == self.robot_id and rec.T_cj_ci is not None:
                n += self.publish(rec.other, rec.T_cj_ci, rec.stamp_s)
        return n
