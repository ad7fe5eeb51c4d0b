"""Where cerpe frames travel on Zenoh: key names, the link header, error replies.

The format itself is described once, in ``docs/online.md``, "Wire format": keys
``cerpe/<team>/<robot>/{descriptor,pose,estimate,bye,image}``, liveliness tokens
``cerpe/<team>/<robot>/alive/v<L>.<M>/<zid>``, a link header as every put's, query's and reply's
attachment, error replies ``header + reason``. Two link protocols: lock-step (``L`` 1, the
4-byte :data:`HEADER`: every robot at the team's step) and by stamps (``L`` 2: the header, then
the frame's capture stamp and the sender's stamp clock, ns, 20 bytes). :class:`Wire` builds and
parses one protocol's; this module also builds and parses the keys.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Any

from ..errors import CerpeError
from ..messages import VERSION as MESSAGES_VERSION
from ..messages import DescriptorMessage, EstimateMessage, ImageReply, ImageRequest, PoseMessage

LINK_PROTOCOL = 1  # lock-step
LINK_STAMPS = 2    # by capture stamps
MAGIC = b"CZ"
HEADER = MAGIC + bytes([LINK_PROTOCOL, MESSAGES_VERSION])
PROTOCOL_TAG = f"v{LINK_PROTOCOL}.{MESSAGES_VERSION}"
ROOT = "cerpe"
SYNC_MODES = ("stamps", "lockstep")
PROTOCOL_OF_MODE = {"lockstep": LINK_PROTOCOL, "stamps": LINK_STAMPS}
_STAMPS = struct.Struct("<qq")  # capture stamp, sender's stamp clock (ns; the clock INT64_MIN: none yet)
_NONE_NS = -(2**63)
LATEST = "latest"  # cerpe/<team>/<robot>/latest/<peer>: the newest estimate, a queryable

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


def alive_key(team: str, robot: str, zid: str, tag: str = PROTOCOL_TAG) -> str:
    return f"{ROOT}/{team}/{robot}/{ALIVE}/{tag}/{zid}"


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


def header_status(attachment: bytes | None, header: bytes = HEADER) -> str:
    """``"ok"``, ``"protocol"`` (our magic, another protocol or version) or ``"garbled"`` (absent or not ours)."""
    if attachment is None or len(attachment) < len(header) or attachment[:2] != MAGIC:
        return "garbled"
    if attachment[:len(header)] != header:
        return "protocol"
    return "ok" if len(attachment) == len(header) else "garbled"


def header_tag(attachment: bytes) -> str:
    """The protocol tag (``v<L>.<M>``) a header announces (for log lines)."""
    return f"v{attachment[2]}.{attachment[3]}" if len(attachment) >= 4 else "v?"


def describe_tag(tag: str) -> str:
    """``v1.2 (lock-step)`` / ``v2.2 (by stamps)``: a protocol tag as a log line names it."""
    proto = tag[1:].split(".")[0]
    mode = {str(LINK_PROTOCOL): "lock-step", str(LINK_STAMPS): "by stamps"}.get(proto)
    return f"{tag} ({mode})" if mode else tag


def error_payload(reason: str, header: bytes = HEADER) -> bytes:
    if reason not in REPLY_ERRORS:
        raise ZenohWireError(f"unknown reply error {reason!r}; known: {REPLY_ERRORS}")
    return header + reason.encode("ascii")


def parse_error_payload(payload: bytes, header: bytes = HEADER) -> str:
    """The reason of an error reply; ``"protocol"`` for another header, ``"garbled"`` for none."""
    status = header_status(payload[: len(header)] if len(payload) >= len(header) else None, header)
    if status != "ok":
        return status
    reason = payload[len(header):].decode("ascii", "replace")
    return reason if reason in REPLY_ERRORS else "garbled"


def _ns(s: float | None) -> int:
    return _NONE_NS if s is None or not s == s else int(round(float(s) * 1e9))


@dataclass(frozen=True)
class Wire:
    """One link protocol's attachments: ``lockstep`` (:data:`HEADER`) or ``stamps`` (header, capture stamp,
    the sender's stamp clock)."""

    mode: str = "lockstep"

    def __post_init__(self) -> None:
        if self.mode not in SYNC_MODES:
            raise ZenohWireError(f"link sync mode {self.mode!r}: expected one of {SYNC_MODES}")

    @property
    def header(self) -> bytes:
        return MAGIC + bytes([PROTOCOL_OF_MODE[self.mode], MESSAGES_VERSION])

    @property
    def tag(self) -> str:
        return f"v{PROTOCOL_OF_MODE[self.mode]}.{MESSAGES_VERSION}"

    @property
    def size(self) -> int:
        return len(self.header) + (_STAMPS.size if self.mode == "stamps" else 0)

    def attachment(self, stamp_s: float | None = None, clock_s: float | None = None) -> bytes:
        """What goes with a put, query or reply: the header (and, by stamps, the stamp and the clock)."""
        if self.mode == "lockstep":
            return self.header
        return self.header + _STAMPS.pack(_ns(0.0 if stamp_s is None else stamp_s), _ns(clock_s))

    def parse(self, attachment: bytes | None) -> tuple[str, float, float]:
        """``(status, capture stamp s, sender's clock s)`` of an attachment; status as :func:`header_status`
        (NaN stamps for lock-step, and for a clock the sender did not have yet)."""
        if attachment is None or len(attachment) < 4 or attachment[:2] != MAGIC:
            return "garbled", float("nan"), float("nan")
        if attachment[:4] != self.header:
            return "protocol", float("nan"), float("nan")
        if len(attachment) != self.size:
            return "garbled", float("nan"), float("nan")
        if self.mode == "lockstep":
            return "ok", float("nan"), float("nan")
        stamp, clock = _STAMPS.unpack(attachment[4:])
        return "ok", stamp * 1e-9, float("nan") if clock == _NONE_NS else clock * 1e-9

    def error_payload(self, reason: str) -> bytes:
        return error_payload(reason, self.header)

    def parse_error_payload(self, payload: bytes) -> str:
        return parse_error_payload(payload, self.header)


def latest_key(team: str, robot: str, peer: str = "*") -> str:
    """``cerpe/<team>/<robot>/latest/<peer>``: the queryable of ``robot``'s newest estimate of ``peer``."""
    return f"{ROOT}/{team}/{robot}/{LATEST}/{peer}"


def as_bytes(z: Any) -> bytes | None:
    """A Zenoh payload or attachment (``ZBytes``) as bytes; None when there is none."""
    return None if z is None else z.to_bytes()
