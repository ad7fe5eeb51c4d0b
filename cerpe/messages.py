"""Messages robots exchange, with an exact wire encoding (bytes are what we count).

Frame layout (little endian), shared by every message type::

    magic  b"CE"   2 B
    version u8     1 B   (VERSION; 2: coded descriptors, the image reply's codec and the sender's pose)
    type    u8     1 B   (1 descriptor, 2 pose, 3 image request, 4 image reply, 5 shared estimates)
    sender  u16    2 B
    step    u32    4 B
    payload        ...
    crc32   u32    4 B   (over everything before it)

The paper's broadcast ``m_i^t = (i, X_i^t, d_i^t)`` travels as two frames. The
:class:`DescriptorMessage` goes before the joint backbone pass (the gate needs it) and
the :class:`PoseMessage` right after it (propagation needs ``X_j^t`` of the same
step). This costs one extra 14-byte header per robot and step and keeps one
backbone pass per step. With ``messages.share_estimates`` (our extension, off in the paper's
rows) a robot also broadcasts, right after its pose, the direct estimates it made this step
(:class:`EstimateMessage`, 62 B each, possibly none). So a robot whose own pass could not
place its peer's image still gets the pair's pose. A garbled frame (bad magic, length or checksum) raises
:class:`MessageError` in :func:`decode`; transports count and drop such frames.
"""
from __future__ import annotations

from .errors import CerpeError
import struct
import zlib
from dataclasses import dataclass
from typing import ClassVar, Union

import numpy as np

from .geometry import GeometryError, se3_from_tq_xyzw, se3_to_tq_xyzw

MAGIC = b"CE"
VERSION = 2  # 1: raw float descriptors, image replies without codec or pose (decoded as another version)
_HEADER = struct.Struct("<2sBBHI")
_CRC = struct.Struct("<I")
# image reply before its bytes: intrinsics 4f | pose_step i32 + pose 7d | codec u8 | length u32 (81 B)
_REPLY_FIXED = struct.Struct("<4fi7dBI")
HEADER_BYTES = _HEADER.size + _CRC.size  # 14

DESCRIPTOR_DTYPES = {"fp32": 0, "fp16": 1, "int8": 2}
# compressed descriptors (cerpe.compress): the payload is an opaque code of a fitted projection
CODED_DESCRIPTOR_DTYPES = {"pca-int8": 3, "pca-pq": 4}
_DTYPE_CODES = {v: k for k, v in {**DESCRIPTOR_DTYPES, **CODED_DESCRIPTOR_DTYPES}.items()}
# image reply codecs; a code the receiver does not know decodes as "unknown-<code>" (counted, not used).
# "-grey": one channel, the mean of the image's three (what XFeat, the offline backbone's features, sees of
# a colour image); the receiver decodes it to three equal channels.
REPLY_CODECS = {"jpeg": 1, "webp": 2, "jpeg-grey": 3, "webp-grey": 4}
JPEG_CODECS = ("jpeg", "jpeg-grey")
_REPLY_CODES = {v: k for k, v in REPLY_CODECS.items()}


class MessageError(CerpeError, ValueError):
    """A frame that cannot be decoded (garbled, truncated, unknown type)."""


def _frame(mtype: int, sender: int, step: int, payload: bytes) -> bytes:
    if not (0 <= sender < 2**16 and 0 <= step < 2**32):
        raise MessageError(f"sender {sender} or step {step} out of range")
    head = _HEADER.pack(MAGIC, VERSION, mtype, sender, step) + payload
    return head + _CRC.pack(zlib.crc32(head) & 0xFFFFFFFF)


@dataclass(frozen=True)
class DescriptorMessage:
    """Robot ``sender``'s global descriptor at ``step``.

    The descriptor is quantised for the wire as ``dtype`` (fp32, fp16 or int8 with
    one fp32 scale); receivers use the decoded, quantised values. A *coded* dtype
    (``pca-int8``, ``pca-pq``: :mod:`cerpe.compress`) carries ``descriptor`` as the
    ``[n] uint8`` code of a fitted projection and quantiser, identified by
    ``codebook`` (u32). Only a :class:`~cerpe.compress.DescriptorCodec` of that
    codebook turns it back into values; the empty code is the zero descriptor.
    """

    TYPE: ClassVar[int] = 1
    sender: int
    step: int
    descriptor: np.ndarray
    dtype: str = "fp16"
    codebook: int = 0

    @property
    def coded(self) -> bool:
        return self.dtype in CODED_DESCRIPTOR_DTYPES

    def encode(self) -> bytes:
        if self.coded:
            code = np.asarray(self.descriptor)
            if code.dtype != np.uint8 or code.ndim != 1:  # the empty code is the zero descriptor (a blank frame)
                raise MessageError(f"coded descriptor ({self.dtype}) must be an [n] uint8 code")
            if not 0 <= int(self.codebook) < 2**32:
                raise MessageError(f"codebook id {self.codebook} out of range")
            head = struct.pack("<BII", CODED_DESCRIPTOR_DTYPES[self.dtype], code.size, int(self.codebook))
            return _frame(self.TYPE, self.sender, self.step, head + code.tobytes())
        d = np.asarray(self.descriptor, dtype=np.float32).ravel()
        if d.size == 0 or not np.all(np.isfinite(d)):
            raise MessageError("descriptor must be non-empty and finite")
        if self.dtype not in DESCRIPTOR_DTYPES:
            raise MessageError(f"descriptor dtype must be one of {list(DESCRIPTOR_DTYPES)}, got {self.dtype!r}")
        head = struct.pack("<BI", DESCRIPTOR_DTYPES[self.dtype], d.size)
        if self.dtype == "fp32":
            body = d.astype("<f4").tobytes()
        elif self.dtype == "fp16":
            body = d.astype("<f2").tobytes()
        else:
            scale = float(np.max(np.abs(d))) / 127.0 or 1.0
            q = np.clip(np.round(d / scale), -127, 127).astype(np.int8)
            body = struct.pack("<f", scale) + q.tobytes()
        return _frame(self.TYPE, self.sender, self.step, head + body)

    @staticmethod
    def wire_bytes(dim: int, dtype: str) -> int:
        """Exact frame size for a descriptor of ``dim`` values in ``dtype`` (coded: ``dim`` code bytes)."""
        if dtype in CODED_DESCRIPTOR_DTYPES:
            return HEADER_BYTES + 9 + dim
        per = {"fp32": 4, "fp16": 2, "int8": 1}[dtype]
        return HEADER_BYTES + 5 + dim * per + (4 if dtype == "int8" else 0)


@dataclass(frozen=True)
class PoseMessage:
    """Robot ``sender``'s metric odometry pose ``X = T_odom_cam`` at ``step`` (float64)."""

    TYPE: ClassVar[int] = 2
    sender: int
    step: int
    T_odom_cam: np.ndarray

    def encode(self) -> bytes:
        try:
            t, q = se3_to_tq_xyzw(self.T_odom_cam)
        except GeometryError as exc:
            raise MessageError(f"pose message: {exc}") from None
        return _frame(self.TYPE, self.sender, self.step, struct.pack("<7d", *t, *q))


_ESTIMATE = struct.Struct("<Hi7d")  # target robot, inliers (-1 unknown), T_cj_ci as t xyz + q xyzw


@dataclass(frozen=True)
class EstimateMessage:
    """The direct estimates robot ``sender`` made at ``step`` (our extension): ``(target, T_cj_ci,
    inliers)`` per peer it placed, ``T_cj_ci`` mapping points of the sender's camera into the
    target's (float64; its inverse is the target's estimate of the sender). May be empty."""

    TYPE: ClassVar[int] = 5
    sender: int
    step: int
    estimates: tuple[tuple[int, np.ndarray, int], ...] = ()

    def encode(self) -> bytes:
        if len(self.estimates) >= 2**16:
            raise MessageError(f"estimate message: {len(self.estimates)} estimates, at most {2**16 - 1}")
        parts = [struct.pack("<H", len(self.estimates))]
        for target, T, inliers in self.estimates:
            if not (0 <= int(target) < 2**16 and -1 <= int(inliers) < 2**31):
                raise MessageError(f"estimate message: target {target} or inliers {inliers} out of range")
            try:
                t, q = se3_to_tq_xyzw(np.asarray(T, dtype=np.float64))
            except GeometryError as exc:
                raise MessageError(f"estimate message: {exc}") from None
            parts.append(_ESTIMATE.pack(int(target), int(inliers), *t, *q))
        return _frame(self.TYPE, self.sender, self.step, b"".join(parts))

    def for_target(self, target: int) -> tuple[np.ndarray, int] | None:
        """``(T_cj_ci, inliers)`` of the estimate about robot ``target`` (the first), None without one."""
        for k, T, inliers in self.estimates:
            if int(k) == int(target):
                return T, int(inliers)
        return None


@dataclass(frozen=True)
class ImageRequest:
    """Robot ``sender`` asks robot ``target`` for its raw image of ``step``."""

    TYPE: ClassVar[int] = 3
    sender: int
    step: int
    target: int

    def encode(self) -> bytes:
        return _frame(self.TYPE, self.sender, self.step, struct.pack("<H", self.target))


@dataclass(frozen=True)
class ImageReply:
    """Robot ``sender``'s image of ``step`` as encoded bytes (``jpeg``: the field keeps its
    name, whatever ``codec`` made them), with its intrinsics and its newest odometry pose.

    ``intrinsics`` is ``(fx, fy, cx, cy)`` in pixels of the encoded image (scaled with
    it when the image was downsized). ``codec`` is one of :data:`REPLY_CODECS`; a
    frame with a codec id this version does not know decodes with ``codec =
    "unknown-<id>"`` so that the receiver can count it and not use the image.
    ``T_odom_cam`` is the sender's odometry pose ``X`` of step ``pose_step`` when it
    answered (its pose of ``step`` when it had one, else of its previous step; -1 and
    None: no pose), so a requester whose copy of the sender's pose message is lost
    can still anchor the pair (see ``docs/extensions.md``, "Message loss").
    """

    TYPE: ClassVar[int] = 4
    sender: int
    step: int
    jpeg: bytes
    intrinsics: tuple[float, float, float, float]
    codec: str = "jpeg"
    pose_step: int = -1
    T_odom_cam: np.ndarray | None = None

    def encode(self) -> bytes:
        if self.codec not in REPLY_CODECS:
            raise MessageError(f"image reply codec must be one of {list(REPLY_CODECS)}, got {self.codec!r}")
        if self.T_odom_cam is None or self.pose_step < 0:
            pose_step, pose = -1, (0, 0, 0, 0, 0, 0, 1)
        else:
            try:
                t, q = se3_to_tq_xyzw(self.T_odom_cam)
            except GeometryError as exc:
                raise MessageError(f"image reply pose: {exc}") from None
            pose_step, pose = int(self.pose_step), (*t, *q)
        payload = _REPLY_FIXED.pack(*self.intrinsics, pose_step, *pose, REPLY_CODECS[self.codec],
                                    len(self.jpeg)) + self.jpeg
        return _frame(self.TYPE, self.sender, self.step, payload)

    @staticmethod
    def from_image(sender: int, step: int, image_rgb: np.ndarray,
                   intrinsics: tuple[float, float, float, float], quality: int = 90,
                   codec: str = "jpeg", scale: float = 1.0, pose_step: int = -1,
                   T_odom_cam: np.ndarray | None = None) -> "ImageReply":
        """Encode ``image_rgb`` with ``codec`` at ``quality`` (0-100), downsized by ``scale``
        (area interpolation; intrinsics scaled to the encoded pixels), with the sender's pose.
        A ``-grey`` codec encodes the mean of the three channels as one (rounded to uint8)."""
        import cv2

        if codec not in REPLY_CODECS:
            raise MessageError(f"image reply codec must be one of {list(REPLY_CODECS)}, got {codec!r}")
        img, K = image_rgb, tuple(float(v) for v in intrinsics)
        if not 0.0 < float(scale) <= 1.0:
            raise MessageError(f"image reply scale must be in (0, 1], got {scale}")
        if scale != 1.0:
            H, W = image_rgb.shape[:2]
            w, h = max(8, int(round(W * scale))), max(8, int(round(H * scale)))
            img = cv2.resize(image_rgb, (w, h), interpolation=cv2.INTER_AREA)
            sx, sy = w / W, h / H  # pixel centres: c' = (c + 0.5) * s - 0.5
            K = (K[0] * sx, K[1] * sy, (K[2] + 0.5) * sx - 0.5, (K[3] + 0.5) * sy - 0.5)
        ext, flag = ((".jpg", cv2.IMWRITE_JPEG_QUALITY) if codec in JPEG_CODECS
                     else (".webp", cv2.IMWRITE_WEBP_QUALITY))
        if codec.endswith("-grey"):
            pixels = np.round(img.mean(axis=2, dtype=np.float32)).astype(np.uint8)
        else:
            pixels = np.ascontiguousarray(img[:, :, ::-1])
        ok, buf = cv2.imencode(ext, pixels, [flag, int(quality)])
        if not ok:
            raise MessageError(f"{codec} encoding failed")
        return ImageReply(sender, step, buf.tobytes(), K, codec=codec, pose_step=int(pose_step),
                          T_odom_cam=None if T_odom_cam is None else np.asarray(T_odom_cam, dtype=np.float64))

    def image_rgb(self) -> np.ndarray:
        import cv2

        if self.codec not in REPLY_CODECS:
            raise MessageError(f"image reply from robot {self.sender} step {self.step}: unknown codec {self.codec}")
        grey = self.codec.endswith("-grey")  # three equal channels (WebP's colour conversion is off by 1)
        arr = cv2.imdecode(np.frombuffer(self.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
        if arr is None:
            raise MessageError(f"image reply from robot {self.sender} step {self.step}: "
                               f"{self.codec} does not decode")
        return np.repeat(arr[:, :, None], 3, axis=2) if grey else arr[:, :, ::-1].copy()


Message = Union[DescriptorMessage, PoseMessage, ImageRequest, ImageReply, EstimateMessage]


def decode(frame: bytes) -> Message:
    """Parse one frame; raises :class:`MessageError` on any inconsistency."""
    if len(frame) < HEADER_BYTES:
        raise MessageError(f"frame too short ({len(frame)} B)")
    body, (crc,) = frame[:-4], _CRC.unpack(frame[-4:])
    if zlib.crc32(body) & 0xFFFFFFFF != crc:
        raise MessageError("checksum mismatch (garbled frame)")
    magic, version, mtype, sender, step = _HEADER.unpack(body[: _HEADER.size])
    if magic != MAGIC or version != VERSION:
        raise MessageError(f"bad magic/version {magic!r}/{version}")
    p = body[_HEADER.size:]
    try:
        if mtype == DescriptorMessage.TYPE:
            code, dim = struct.unpack("<BI", p[:5])
            dtype = _DTYPE_CODES.get(code)
            if dtype is None:
                raise MessageError(f"unknown descriptor dtype code {code}")
            if dtype in CODED_DESCRIPTOR_DTYPES:
                (book,) = struct.unpack("<I", p[5:9])
                if len(p) != 9 + dim:
                    raise MessageError("coded descriptor length does not match its code size")
                return DescriptorMessage(sender, step, np.frombuffer(p[9:], np.uint8).copy(), dtype, book)
            raw = p[5:]
            if dtype == "fp32":
                d = np.frombuffer(raw, "<f4", count=dim).astype(np.float32)
                rest = raw[4 * dim:]
            elif dtype == "fp16":
                d = np.frombuffer(raw, "<f2", count=dim).astype(np.float32)
                rest = raw[2 * dim:]
            else:
                (scale,) = struct.unpack("<f", raw[:4])
                d = np.frombuffer(raw[4:], np.int8, count=dim).astype(np.float32) * scale
                rest = raw[4 + dim:]
            if rest:
                raise MessageError("descriptor frame has trailing bytes")
            return DescriptorMessage(sender, step, d, dtype)
        if mtype == PoseMessage.TYPE:
            if len(p) != 56:
                raise MessageError("pose frame has wrong length")
            v = struct.unpack("<7d", p)
            if not np.all(np.isfinite(v)):
                raise MessageError("pose frame carries non-finite values")
            return PoseMessage(sender, step, se3_from_tq_xyzw(v[:3], v[3:]))
        if mtype == EstimateMessage.TYPE:
            (n,) = struct.unpack("<H", p[:2])
            if len(p) != 2 + n * _ESTIMATE.size:
                raise MessageError("estimate frame length does not match its count")
            ests = []
            for k in range(n):
                target, inliers, *v = _ESTIMATE.unpack_from(p, 2 + k * _ESTIMATE.size)
                if not np.all(np.isfinite(v)) or inliers < -1:
                    raise MessageError("estimate frame carries non-finite values or negative inliers")
                ests.append((int(target), se3_from_tq_xyzw(v[:3], v[3:]), int(inliers)))
            return EstimateMessage(sender, step, tuple(ests))
        if mtype == ImageRequest.TYPE:
            if len(p) != 2:
                raise MessageError("image request has wrong length")
            return ImageRequest(sender, step, struct.unpack("<H", p)[0])
        if mtype == ImageReply.TYPE:
            fx, fy, cx, cy, pose_step, *v, ccode, n = _REPLY_FIXED.unpack(p[:_REPLY_FIXED.size])
            if len(p) != _REPLY_FIXED.size + n:
                raise MessageError("image reply length does not match its image size")
            if not np.all(np.isfinite(v)):
                raise MessageError("image reply pose carries non-finite values")
            T = None if pose_step < 0 else se3_from_tq_xyzw(v[:3], v[3:])
            return ImageReply(sender, step, bytes(p[_REPLY_FIXED.size:]), (fx, fy, cx, cy),
                              codec=_REPLY_CODES.get(ccode, f"unknown-{ccode}"),
                              pose_step=max(int(pose_step), -1), T_odom_cam=T)
    except (struct.error, ValueError, GeometryError) as exc:
        if isinstance(exc, MessageError):
            raise
        raise MessageError(f"malformed payload for type {mtype}: {exc}") from None
    raise MessageError(f"unknown message type {mtype}")
