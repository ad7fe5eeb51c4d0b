"""One robot's frame on its way in: checks, the descriptor, the blank-frame test, received images."""
from __future__ import annotations

import time
from collections import Counter

import numpy as np

from ..messages import JPEG_CODECS, REPLY_CODECS, ImageReply, MessageError
from ..protocols import DescriptorEncoder, FrameContext, View
from ..scene import CameraIntrinsics
from .config import AlgorithmError


def check_frame(image: np.ndarray, context: FrameContext, where: str) -> np.ndarray:
    """The image as an ``[H,W,3] uint8`` array consistent with its intrinsics and sensor depth."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
        raise AlgorithmError(f"{where}: image must be a non-empty [H,W,3] array, got shape {img.shape}")
    if img.dtype != np.uint8:
        raise AlgorithmError(f"{where}: image must be uint8 RGB, got dtype {img.dtype}")
    H, W = img.shape[:2]
    K = context.intrinsics
    if K is not None and (int(K.width), int(K.height)) != (W, H):
        raise AlgorithmError(f"{where}: intrinsics are for {K.width}x{K.height} but the image is {W}x{H}")
    if context.sensor_depth_m is not None:
        d = np.asarray(context.sensor_depth_m)
        if d.shape != (H, W):
            raise AlgorithmError(f"{where}: sensor_depth_m shape {d.shape} does not match the image {(H, W)}")
    return img


def grey_std(image: np.ndarray) -> float:
    """Standard deviation of the grey level (mean of the channels) over every other pixel."""
    return float(image[::2, ::2].mean(axis=2, dtype=np.float32).std())


def describe(descriptor: DescriptorEncoder, view: View, where: str,
             min_image_std: float) -> tuple[np.ndarray, str, Counter, Counter]:
    """``([D] float32 descriptor, why the frame is blank or "", stage wall seconds, stage CPU seconds)``.

    Blank: the descriptor flags it ``low-texture`` (``flags(view)``, when it has
    one), has zero norm, or the image's grey-level std is below ``min_image_std``
    (so every descriptor is covered, also one that returns a random unit vector
    for a blank image). The split into ``encode`` and ``descriptor`` is the
    descriptor's own (``last_timings_s``, ``last_cpu_s``) when it gives one.
    """
    t0, c0 = time.perf_counter(), time.thread_time()
    d = np.asarray(descriptor.describe(view), dtype=np.float32)
    split = getattr(descriptor, "last_timings_s", None)
    split_cpu = getattr(descriptor, "last_cpu_s", None)
    flags = getattr(descriptor, "flags", None)
    low_texture = callable(flags) and "low-texture" in (flags(view) or ())
    dim = int(getattr(descriptor, "dim", d.size))
    if d.ndim != 1 or d.size != dim:
        raise AlgorithmError(f"{where}: descriptor has shape {d.shape}, expected [{dim}]")
    if not np.all(np.isfinite(d)):
        raise AlgorithmError(f"{where}: descriptor contains NaN or inf")
    blank = ("zero-norm" if not np.linalg.norm(d) > 0 else "low-texture" if low_texture
             else "low-std" if grey_std(view.image) < min_image_std else "")
    timings: Counter = Counter()
    cpu: Counter = Counter()
    if isinstance(split, dict) and "encode" in split and "descriptor" in split:
        timings["encode"] += float(split["encode"])
        timings["descriptor"] += float(split["descriptor"])
    else:  # the whole call, flags and the texture check included
        timings["descriptor"] += time.perf_counter() - t0
    if isinstance(split_cpu, dict) and "encode" in split_cpu and "descriptor" in split_cpu:
        cpu["encode"] += float(split_cpu["encode"])
        cpu["descriptor"] += float(split_cpu["descriptor"])
    else:
        cpu["descriptor"] += time.thread_time() - c0
    return d, blank, timings, cpu


def intrinsics_tuple(K: CameraIntrinsics | None) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` for an image reply; ``(0, 0, 0, 0)`` means unknown (``fx`` is never 0)."""
    return (0.0, 0.0, 0.0, 0.0) if K is None else (K.fx, K.fy, K.cx, K.cy)


#: Largest distance of a reply's principal point from the image centre, as a fraction of the
#: image size, before the image counts as being of another size than its intrinsics. The reply
#: carries ``fx, fy, cx, cy`` but no size; a 2x resize moves ``cx`` by a quarter of the width.
MAX_PRINCIPAL_OFFSET = 0.2


def jpeg_truncated(jpeg: bytes) -> bool:
    """True when the JPEG has no end-of-image marker after its last scan.

    A truncated JPEG often still "decodes" (the decoder fills the missing rows
    with grey), so the end marker is checked before decoding. Inside a scan 0xFF
    is always followed by 0x00 or a restart marker, so ``FF D9`` after the last
    start-of-scan ``FF DA`` can only be the end marker.
    """
    end = jpeg.rfind(b"\xff\xd9")
    return end < 0 or end < jpeg.rfind(b"\xff\xda")


def received_view(other: str, reply: ImageReply) -> tuple[View | None, str]:
    """A collaborator's JPEG as a :class:`View` keyed ``(other, step, "jpeg")``, or ``(None, fault)``.

    The key differs from the owner's ``(other, step)`` because the pixels do:
    plug-ins shared by a simulated team may cache per key and must not mix the
    raw and the decoded image. Faults (counted as ``msg:<fault>`` by the robot):

    * ``unknown-reply-codec``: a codec id this version does not know;
    * ``truncated-jpeg``: no end marker;
    * ``undecodable-jpeg``: the image (JPEG or WebP) does not decode;
    * ``image-size-mismatch``: the principal point of the reply's intrinsics lies more than
      :data:`MAX_PRINCIPAL_OFFSET` of the size off the decoded image's centre, or the image
      is smaller than 8x8 pixels.
    """
    if reply.codec not in REPLY_CODECS:  # a codec of another version: cannot be decoded here
        return None, "unknown-reply-codec"
    if reply.codec in JPEG_CODECS and not reply.jpeg.startswith(b"\xff\xd8"):  # no start-of-image marker
        return None, "undecodable-jpeg"
    if reply.codec in JPEG_CODECS and jpeg_truncated(reply.jpeg):
        return None, "truncated-jpeg"
    try:
        img = reply.image_rgb()
    except MessageError:
        return None, "undecodable-jpeg"
    H, W = img.shape[:2]
    fx, fy, cx, cy = reply.intrinsics
    K = None
    if fx > 0 and fy > 0 and np.all(np.isfinite(reply.intrinsics)):
        if (min(H, W) < 8 or abs(cx - (W - 1) / 2) > MAX_PRINCIPAL_OFFSET * W
                or abs(cy - (H - 1) / 2) > MAX_PRINCIPAL_OFFSET * H):
            return None, "image-size-mismatch"
        K = CameraIntrinsics(fx, fy, cx, cy, W, H)
    elif min(H, W) < 8:
        return None, "image-size-mismatch"
    return View(key=(other, reply.step, "jpeg"), image=img, intrinsics=K), ""
