"""Where cerpe frames travel on Zenoh: key names, the 4-byte link header, error replies.

The format itself is described once, in ``docs/online.md``, "Keys on Zenoh" and
"Wire format": keys ``cerpe/<team>/<robot>/{descriptor,pose,bye,image}``, liveliness
tokens ``cerpe/<team>/<robot>/alive/v<L>.<M>/<zid>``, :data:`HEADER` as every put's,
query's and reply's attachment, error replies ``HEADER + reason``. This module builds
and parses them.
"""
from __future__ import annotations

import re
from typing import Any

from ..errors import CerpeError
from ..messages import VERSION as MESSAGES_VERSION
from ..messages import DescriptorMessage, EstimateMessage, ImageReply, ImageRequest, PoseMessage

LINK_PROTOCOL = 1
MAGIC = b"CZ"
HEADER = MAGIC + bytes([LINK_PROTOCOL, MESSAGES_VERSION])
PROTOCOL_TAG = f"v{LINK_PROTOCOL}.{MESSAGES_VERSION}"
ROOT = "cerpe"

# message type byte -> the kind name cerpe.transport uses; "image" is the queryable's key
KIND_OF_TYPE: dict[int, str] = {DescriptorMessage.TYPE: "descriptor", PoseMessage.TYPE: "pose",
                                ImageRequest.TYPE: "request", ImageReply.TYPE: "reply",
                                EstimateMessage.TYPE: "estimate"}
BROADCAST_KINDS: tuple[str, ...] = ("descriptor", "pose", "estimate")
BYE = "bye"
IMAGE = "image"
ALIVE = "alive"

# error replies of the image queryable
NOT_HELD = "not-held"          # the owner no longer holds the image of that step
REPLY_ERRORS = (NOT_HELD, "garbled", "wrong-target", "protocol", "busy", "error")

_CHUNK = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$")


class ZenohWireError(CerpeError, ValueError):
    """A team or robot name that cannot be a key chunk."""


def check_chunk(name: str, what: str) -> str:
    """``name`` if it can be one key chunk (letters, digits, ``_ . -``; not starting with ``.``/``-``)."""
    s = str(name)
    if not _CHUNK.match(s):
        raise ZenohWireError(f"{what} {name!r}: must be 1-64 letters, digits, '_', '.' or '-' "
                             f"(not starting with '.' or '-'), as it is a Zenoh key chunk")
    return s


def data_key(team: str, robot: str, kind: str) -> str:
    return f"{ROOT}/{team}/{robot}/{kind}"


def team_keys(team: str) -> str:
    """What a robot of ``team`` subscribes to."""
    return f"{ROOT}/{team}/*/*"


def image_key(team: str, robot: str) -> str:
    return data_key(team, robot, IMAGE)


def alive_key(team: str, robot: str, zid: str) -> str:
    return f"{ROOT}/{team}/{robot}/{ALIVE}/{PROTOCOL_TAG}/{zid}"


ALIVE_ALL = f"{ROOT}/*/*/{ALIVE}/**"


def parse_data_key(key: str) -> tuple[str, str, str] | None:
    """``cerpe/<team>/<robot>/<kind>`` -> ``(team, robot, kind)``; None for any other key."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != ROOT:
        return None
    return parts[1], parts[2], parts[3]


def parse_alive_key(key: str) -> tuple[str, str, str, str] | None:
    """A liveliness key -> ``(team, robot, protocol tag, zid)``; None if it is not one of ours."""
    parts = str(key).split("/")
    if len(parts) != 6 or parts[0] != ROOT or parts[3] != ALIVE:
        return None
    return parts[1], parts[2], parts[4], parts[5]


def header_status(attachment: bytes | None) -> str:
    """``"ok"``, ``"protocol"`` (our magic, another version) or ``"garbled"`` (absent or not ours)."""
    if attachment is None or len(attachment) != len(HEADER) or attachment[:2] != MAGIC:
        return "garbled"
    return "ok" if attachment == HEADER else "protocol"


def header_tag(attachment: bytes) -> str:
    """The protocol tag (``v<L>.<M>``) a header announces (for log lines)."""
    return f"v{attachment[2]}.{attachment[3]}" if len(attachment) >= 4 else "v?"


def error_payload(reason: str) -> bytes:
    if reason not in REPLY_ERRORS:
        raise ZenohWireError(f"unknown reply error {reason!r}; known: {REPLY_ERRORS}")
    return HEADER + reason.encode("ascii")


def parse_error_payload(payload: bytes) -> str:
    """The reason of an error reply; ``"protocol"`` for another header, ``"garbled"`` for none."""
    status = header_status(payload[: len(HEADER)] if len(payload) >= len(HEADER) else None)
    if status != "ok":
        return status
    reason = payload[len(HEADER):].decode("ascii", "replace")
    return reason if reason in REPLY_ERRORS else "garbled"


def as_bytes(z: Any) -> bytes | None:
    """A Zenoh payload or attachment (``ZBytes``) as bytes; None when there is none."""
    return None if z is None else z.to_bytes()
