"""The ROS 2 type store and the message types cerpe reads and writes, with CDR (de)serialisation.

Every ROS 2 distribution shares the definitions of these types, so one store (Jazzy's) serves all;
ROS 1 messages in ``.bag`` files are turned into the same classes by ``rosbags`` (field names differ
only in ``CameraInfo``: ``D K R P`` there, ``d k r p`` in ROS 2; :mod:`cerpe.rosio.decode` reads both).
"""
from __future__ import annotations

import functools
from typing import Any

from ..errors import CerpeError

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"

#: the types a camera image topic may carry
IMAGE_TYPES: tuple[str, ...] = (IMAGE, COMPRESSED_IMAGE)
#: the types a ground-truth or odometry topic may carry (a pose of a body in a world or odom frame)
POSE_TYPES: tuple[str, ...] = (POSE_STAMPED, POSE_COV_STAMPED, TRANSFORM_STAMPED, ODOMETRY)


class RosInputError(CerpeError, ValueError):
    """A ROS message that cannot be used: wrong type, unsupported encoding, bad numbers (names the field)."""


@functools.lru_cache(maxsize=1)
def typestore() -> Any:
    """The ``rosbags`` type store of ROS 2 Jazzy (these message definitions are the same in every distro)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def msg_class(msgtype: str) -> Any:
    """The ``rosbags`` class of ``msgtype`` (e.g. ``sensor_msgs/msg/Image``)."""
    try:
        return typestore().types[msgtype]
    except KeyError:
        raise RosInputError(f"unknown ROS message type {msgtype!r}") from None


def deserialize(cdr: bytes, msgtype: str, what: str) -> Any:
    """A CDR payload (with its 4-byte encapsulation header) as a ``msgtype`` message; one
    :class:`RosInputError` naming ``what`` (a topic) when it is not one."""
    try:
        return typestore().deserialize_cdr(bytes(cdr), msgtype)
    except Exception as exc:  # noqa: BLE001 -- rosbags raises several types for foreign or truncated data
        raise RosInputError(f"{what}: not a CDR {msgtype} ({type(exc).__name__}: {exc})") from None


def serialize(msg: Any, msgtype: str) -> bytes:
    """``msg`` as CDR (little endian, with its encapsulation header)."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def dds_type_name(msgtype: str) -> str:
    """``pkg/msg/Name`` as DDS (and rmw_zenoh's keys) name it: ``pkg::msg::dds_::Name_``."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str | None:
    """The inverse of :func:`dds_type_name`; None for a name that is not one."""
    parts = dds_name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        return None
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def type_hash(msgtype: str) -> str:
    """The ``RIHS01_...`` type hash ROS 2 Jazzy and later give ``msgtype``."""
    return typestore().hash_rihs01(msgtype)
